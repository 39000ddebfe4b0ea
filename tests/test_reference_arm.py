"""The generated C on ARM: cross-compiled for an ARM Linux target (armhf, Thumb-2, hard
float) and run under qemu-user, bit for bit against the NumPy reference; and compiled
for a Cortex-M4 (Thumb-2, FPv4-SP hard float), whose step is counted instruction by
instruction (benchmarks/observer_arm.py prints the table). The toolchains are Debian's
`gcc-arm-linux-gnueabihf`, `libc6-dev-armhf-cross`, `qemu-user`, `gcc-arm-none-eabi`
and `libnewlib-arm-none-eabi`
(`.ci/run` installs them, and fails if it cannot). Without them a test is skipped, naming
the missing tool, on a developer's machine; in CI (environment `CI=true`, which `.ci/run`
sets) it fails instead, so that a broken toolchain install cannot pass as a green run.
The armhf executable's target is read from its ELF header here (no `file` tool needed)."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

import thermojax.reference as ref
from thermojax.reference._arm import M4_FLAGS, count_step_instructions

from test_reference_c import FAULTS, faulted_playback
from test_reference_setup import IMU6_SCALING

LINUX_CC, QEMU, M4_CC = "arm-linux-gnueabihf-gcc", "qemu-arm", "arm-none-eabi-gcc"
STEPS = 6000
WARN = ["-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror", "-ffp-contract=off"]


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def _need(*tools):
    """Skip (fail in CI) when a toolchain program is missing."""
    missing = [t for t in tools if shutil.which(t) is None]
    if missing:
        why = (f"{', '.join(missing)} not installed (Debian: gcc-arm-linux-gnueabihf, "
               "libc6-dev-armhf-cross, qemu-user, gcc-arm-none-eabi, libnewlib-arm-none-eabi; "
               ".ci/run installs them)")
        if _in_ci():
            pytest.fail(f"CI=true: {why}", pytrace=False)
        pytest.skip(why)


def _elf_machine(path) -> tuple[int, int]:
    """`(EI_CLASS, e_machine)` of an ELF file, read from its header (ELF spec: magic
    `\x7fELF`, class at byte 4 (1: 32-bit), data at byte 5 (1: little-endian), e_machine
    the half-word at byte 18; 40 is EM_ARM)."""
    head = Path(path).read_bytes()[:20]
    assert head[:4] == b"\x7fELF", head[:4]
    endian = "<" if head[5] == 1 else ">"
    return head[4], struct.unpack(endian + "H", head[18:20])[0]


def test_need_fails_in_ci_and_skips_elsewhere(monkeypatch, tmp_path):
    """The switch itself: a missing tool is a failure under CI=true, a skip otherwise; and
    the ELF reader on a hand-made 32-bit little-endian ARM header."""
    fake = tmp_path / "fake.elf"
    fake.write_bytes(b"\x7fELF" + bytes([1, 1, 1]) + bytes(9) + struct.pack("<HH", 2, 40))
    assert _elf_machine(fake) == (1, 40)
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="no-such-compiler-xyz"):
        _need("no-such-compiler-xyz")
    monkeypatch.setenv("CI", "")
    with pytest.raises(pytest.skip.Exception, match="no-such-compiler-xyz"):
        _need("no-such-compiler-xyz")


def _observers():
    system, u, y, x0, oc = faulted_playback()
    u, y, oc = u[:STEPS], y[:STEPS], oc[:STEPS] | np.isnan(y[:STEPS])
    obs = {"float64": ref.FloatObserver(system, FAULTS, dtype=np.float64),
           "float32": ref.FloatObserver(system, FAULTS, dtype=np.float32)}
    for fmt in ("q16.16", "q8.24", "q31"):
        obs[fmt] = ref.FixedObserver(system, fmt, IMU6_SCALING[fmt], FAULTS)
    return obs, (x0, u, y, oc)


@pytest.mark.parametrize("build", ["float64", "float32", "q16.16", "q8.24", "q31"])
def test_armhf_build_under_qemu_is_bit_exact(build, tmp_path):
    _need(LINUX_CC, QEMU)
    observers, (x0, u, y, oc) = _observers()
    obs = observers[build]
    if build.startswith("q"):
        x0, u, y = obs.encode_states(x0), obs.encode_inputs(u), obs.encode_outputs(y)
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs")
    paths = src.write(tmp_path)
    exe = tmp_path / "obs_arm"
    subprocess.run([LINUX_CC, *WARN, "-static", "-mthumb", "-march=armv7-a",
                    "-mfpu=vfpv3-d16", "-mfloat-abi=hard", "-o", str(exe),
                    str(paths["source"]), str(paths["harness"]), "-lm"], check=True,
                   capture_output=True, text=True)
    assert _elf_machine(exe) == (1, 40)  # ELFCLASS32, EM_ARM
    (tmp_path / "in.bin").write_bytes(src.pack_playback(x0, u, y, oc))
    subprocess.run([QEMU, str(exe), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")],
                   check=True, timeout=300)
    got = src.unpack_output((tmp_path / "out.bin").read_bytes())
    assert len(set(want.in_use.tolist())) >= 2          # a channel was dropped
    assert np.array_equal(got.states.astype(want.states.dtype), want.states)
    assert np.array_equal(got.residuals.astype(want.residuals.dtype), want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


@pytest.mark.parametrize("build", ["float32", "q16.16", "q31"])
def test_cortex_m4_build_compiles_and_is_counted(build, tmp_path):
    _need(M4_CC)
    observers, _ = _observers()
    src = ref.generate_c(observers[build], "obs")
    paths = src.write(tmp_path)
    obj = tmp_path / "obs_m4.o"
    subprocess.run([M4_CC, *WARN, *M4_FLAGS, "-c", "-o", str(obj), str(paths["source"])],
                   check=True, capture_output=True, text=True)
    count = count_step_instructions(obj, "obs")
    # the step's multiply-accumulates alone (nonzero coefficients of [Phi B0 B1], [C D]
    # and the full gain) are a floor: at least one instruction each
    s = observers[build].system
    macs = sum(int(np.count_nonzero(M)) for M in (np.hstack([s.Phi, s.B0, s.B1]),
                                                   np.hstack([s.C, s.D]), s.L))
    assert count["instructions"] >= macs
    if build == "float32":   # single-precision FPU instructions, no double-precision calls
        assert count["fpu"] > 0 and count["soft_float_calls"] == 0


def _run_armhf(src, tmp_path, data: bytes, exe_name: str):
    """Cross-compile `src` (a `CSource`) for armhf, play `data` under qemu, return the
    output bytes."""
    paths = src.write(tmp_path)
    exe = tmp_path / exe_name
    subprocess.run([LINUX_CC, *WARN, "-static", "-mthumb", "-march=armv7-a",
                    "-mfpu=vfpv3-d16", "-mfloat-abi=hard", "-o", str(exe),
                    str(paths["source"]), str(paths["harness"]), "-lm"], check=True,
                   capture_output=True, text=True)
    (tmp_path / "in.bin").write_bytes(data)
    subprocess.run([QEMU, str(exe), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")],
                   check=True, timeout=300)
    return (tmp_path / "out.bin").read_bytes()


def test_adaptive_filter_under_qemu_is_bit_exact_and_compiles_for_the_m4(tmp_path):
    """The firmware adaptive filter (double, `sqrt`, LU solves) on armhf under qemu, bit
    for bit against `AdaptiveReference` through a flagged delamination; and its object for
    the Cortex-M4 (double in software there: FPv4-SP has no double unit)."""
    _need(LINUX_CC, QEMU, M4_CC)
    from test_adaptive_filter import ATTACH, DT, MODEL, truth

    from thermojax.io import parse_model
    from thermojax.observer import adaptive_design

    design = adaptive_design(parse_model(MODEL), [ATTACH], DT, drift=2e-4, ceiling=0.5,
                             substeps=2)
    t, u, x, y = truth(lambda s: 0.05 if s < 1800 else 0.025, 3600, seed=6)
    want = ref.AdaptiveReference(design).run(x[0], u, y)
    assert want.flags.any()
    src = ref.generate_adaptive_c(design, "tj_adaptive")
    got = ref.unpack_adaptive(_run_armhf(src, tmp_path, ref.pack_adaptive(x[0], u, y),
                                         "adaptive_arm"), design.n, design.k)
    for field in ("states", "conductances", "variances", "nis", "flags"):
        assert np.array_equal(getattr(got, field), getattr(want, field)), field
    obj = tmp_path / "adaptive_m4.o"
    subprocess.run([M4_CC, *WARN, *M4_FLAGS, "-c", "-o", str(obj),
                    str(tmp_path / "tj_adaptive.c")], check=True, capture_output=True,
                   text=True)
    assert count_step_instructions(obj, "tj_adaptive")["soft_float_calls"] > 0


def test_fixed_multirate_under_qemu_is_bit_exact(tmp_path):
    """The fixed build's integer ramps (`word="int32_t"`, int64 floor division) on armhf
    under qemu, bit for bit against `run_multirate`'s integer interpolator, with ramps of
    both signs, ties and jitter; and no floating point in the Cortex-M4 object."""
    _need(LINUX_CC, QEMU, M4_CC)
    rng = np.random.default_rng(7)
    T, q, ratio = 400, 3, 40
    bias = np.cumsum(rng.integers(-(1 << 20), 1 << 20, (T, q)), axis=0)
    bias[50:60] = bias[49]                       # holds: zero-length ramps
    b0 = bias[0] - 12345
    delay = rng.integers(0, ratio, T)
    reader = ref.BiasInterpolator(q, ratio, initial=b0, codes=True)
    buf = ref.DoubleBuffer(q, np.int64)
    want, k = np.empty((T * ratio, q), np.int64), 0
    at = np.arange(T) * ratio + delay
    for t in range(T * ratio):
        while k < T and at[k] == t:
            buf.publish(bias[k])
            k += 1
        want[t] = reader.tick(buf)
    src = ref.generate_multirate_c("mr", q, ratio, word="int32_t")
    out = _run_armhf(src, tmp_path, ref.pack_multirate(b0, bias, delay, word="int32_t"),
                     "mr_arm")
    assert np.array_equal(np.frombuffer(out, np.int32).reshape(-1, q).astype(np.int64), want)
    obj = tmp_path / "mr_m4.o"
    subprocess.run([M4_CC, *WARN, *M4_FLAGS, "-c", "-o", str(obj), str(tmp_path / "mr.c")],
                   check=True, capture_output=True, text=True)
    disasm = subprocess.run(["arm-none-eabi-objdump", "-d", str(obj)], check=True,
                            capture_output=True, text=True).stdout
    assert "vadd" not in disasm and "vmul" not in disasm and "__aeabi_d" not in disasm


def test_scheduled_observer_under_qemu_is_bit_exact(tmp_path):
    """The gain-scheduled observer's C (interpolated tables, double) on armhf under qemu,
    bit for bit against `ScheduledObserver`, across every interval, clamped at both ends,
    with a dropout of the scheduling sensor."""
    _need(LINUX_CC, QEMU)
    from test_gain_scheduling import DT, MODEL

    from thermojax.io import parse_model
    from thermojax.observer import scheduled_design

    design = scheduled_design(parse_model(MODEL), 1 / DT, [-40, 0, 40, 85], "T_board")
    T = 3000
    t = np.arange(T) * DT
    ch = 22.5 - 80 * np.cos(2 * np.pi * t / (T * DT))        # past both ends of the points
    u = np.stack([ch, np.where((t // 600) % 2 == 0, 0.1, 0.4)], axis=1)
    rng = np.random.default_rng(8)
    y = np.stack([ch + 2.0, ch + 0.5], axis=1) + 0.01 * rng.standard_normal((T, 2))
    y[500:520, 0] = np.nan
    x0 = np.array([ch[0] + 4.0, ch[0] + 2.0, ch[0] + 0.5])
    want = ref.ScheduledObserver(design).run(x0, u, y)
    assert want.s.min() == -40.0 and want.s.max() == 85.0
    src = ref.generate_scheduled_c(design, "tj_scheduled")
    got = ref.unpack_scheduled(_run_armhf(src, tmp_path, ref.pack_scheduled(x0, u, y),
                                          "sched_arm"), 3)
    assert np.array_equal(got.states, want.states) and np.array_equal(got.s, want.s)


def test_trimmed_observer_under_qemu_is_bit_exact(tmp_path):
    """The end-of-line trimmed observer's C (tables interpolated once at init, double) on
    armhf under qemu, bit for bit against `TrimmedObserver`, at a unit's factors between
    grid points and with an erased (NaN) factor."""
    _need(LINUX_CC, QEMU)
    from test_trim import TRIM, TRUTH, spec_text, unit_states

    from thermojax.io import parse_model
    from thermojax.measurements import builtin_profile
    from thermojax.observer import parse_trim_plan, trim_design

    spec = parse_model(spec_text())
    design = trim_design(spec, 1.0, parse_trim_plan(TRIM, spec))
    p = builtin_profile("eol_sweep")
    u = np.stack([p.temperature, p.power], axis=1)
    x = unit_states(*TRUTH, u, 1.0)
    y = x[:, 1:] + 0.01 * np.random.default_rng(9).standard_normal((len(u), 2))
    src = ref.generate_trimmed_c(design, "tj_trimmed")
    for k, f in enumerate((TRUTH, (np.nan, 0.9))):
        want = ref.TrimmedObserver(design, f).run(x[0], u, y)
        got = ref.unpack_trimmed(_run_armhf(src, tmp_path, ref.pack_trimmed(f, x[0], u, y),
                                            f"trim_arm{k}"), 3)
        assert np.array_equal(got, want), f
