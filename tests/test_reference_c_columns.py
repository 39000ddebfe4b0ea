"""The generated C in the column layout (`generate_c(layout="columns")`, SIMD across rows)
against the NumPy float reference: bit for bit up to the sign of an exact zero, compiled
without vectorization (-O0, -O2 -fno-tree-vectorize) and vectorized (-O3 -march=x86-64-v3,
AVX2), over a long playback with fault injections."""

import subprocess

import numpy as np
import pytest

from test_reference_bias_fixed import FAULTS as BIAS_FAULTS, artifact, faulted  # noqa: F401
from test_reference_c import FAULTS, faulted_playback
from test_reference_setup import IMU6_SCALING, gcc_build, gcc_run, playback

import thermojax.reference as ref

AVX2 = ("-O3", "-march=x86-64-v3")
FLAGS = [("-O0",), ("-O2", "-fno-tree-vectorize"), AVX2]


def cpu_has_x86_64_v3(folder) -> bool:
    """Whether this CPU runs `-march=x86-64-v3` code (AVX2, FMA, BMI2, ...): asked at run
    time through gcc's `__builtin_cpu_supports`."""
    probe = folder / "probe.c"
    probe.write_text('int main(void) { __builtin_cpu_init(); '
                     'return !__builtin_cpu_supports("x86-64-v3"); }\n')
    built = subprocess.run(["gcc", "-o", str(folder / "probe"), str(probe)], capture_output=True)
    return built.returncode == 0 and subprocess.run([str(folder / "probe")]).returncode == 0


def same_up_to_zero_sign(a, b) -> bool:
    """Bit for bit, except that `-0` equals `+0` (`v + 0` turns `-0` into `+0` and leaves
    every other value, NaN included, as it is)."""
    a, b = np.asarray(a) + 0, np.asarray(b) + 0
    bits = {4: np.uint32, 8: np.uint64}[a.dtype.itemsize]
    return a.dtype == b.dtype and np.array_equal(a.view(bits), b.view(bits))


def sparse(system):
    """imu6 with its small coefficients set to zero (Phi below 1e-8, B0 and B1 below 1e-9,
    gains below 1e-3) and the last state's gain row zero in every subset: columns with
    zeros in some rows, rows without gain terms."""
    cut = lambda a, t: np.where(np.abs(a) < t, 0.0, a)
    p = system.n_outputs
    gains = {}
    for mask in range(1, 1 << p):
        used = [j for j in range(p) if mask >> j & 1]
        L = cut(system.gain_table[mask][:, used], 1e-3)
        L[-1] = 0.0
        gains[tuple(used)] = L
    return ref.ObserverSystem.build(cut(system.Phi, 1e-8), cut(system.B0, 1e-9),
                                    cut(system.B1, 1e-9), system.C, system.D, gains)


SYSTEMS = {"imu6": lambda s: s, "sparse": sparse}


def nonfinite_playback():
    """`faulted_playback` plus measurements that are NaN or infinite while
    their channel is in use before and after (a channel not in use is skipped)."""
    system, u, y, x0, oc = faulted_playback()
    y[30000:30050, 1] = np.nan
    y[31000:31020, 0] = np.inf
    y[32000:32010, 2] = -np.inf
    return system, u, y, x0, oc


@pytest.mark.parametrize("system_kind", SYSTEMS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("flags", FLAGS, ids=lambda f: "".join(f))
def test_columns_c_bit_exact(system_kind, dtype, flags, tmp_path):
    if flags == AVX2 and not cpu_has_x86_64_v3(tmp_path):
        pytest.skip("this CPU does not run -march=x86-64-v3 code (AVX2)")
    system, u, y, x0, oc = nonfinite_playback()
    system = SYSTEMS[system_kind](system)
    obs = ref.FloatObserver(system, FAULTS, dtype=dtype)
    want = obs.run(x0, u, y, oc)
    assert len(set(want.in_use.tolist())) >= 4 and want.wire_break.any()
    assert np.isnan(want.residuals).any()
    src = ref.generate_c(obs, "obs", layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y, oc)
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.residuals, want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_columns_exact_zeros(dtype, tmp_path):
    """Exact zeros of either sign through a two-state system with zeros inside its columns
    (`x0' = x1`, `x1' = u - x0 / 2`): the column sums add the zero products that the row
    sums skip, which changes the sign of some zero results, and nothing else: every value
    compares equal, the flags agree."""
    system = ref.ObserverSystem.build([[0.0, 1.0], [-0.5, 0.0]], [[0.0], [1.0]], [[0.0], [0.0]],
                                      [[1.0, 0.0]], [[0.0]], {(0,): [[0.5], [0.0]]})
    T = 400
    rng = np.random.default_rng(5)
    signed_zeros = lambda *shape: np.where(rng.random(shape) < 0.5, -0.0, 0.0)
    u, y, x0 = signed_zeros(T, 1), signed_zeros(T, 1), signed_zeros(2)
    oc = rng.random((T, 1)) < 0.1
    obs = ref.FloatObserver(system, ref.FaultConfig(recover_after=3), dtype=dtype)
    want = obs.run(x0, u, y, oc)
    assert len(set(want.in_use.tolist())) == 2
    src = ref.generate_c(obs, "obs", layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *FLAGS[1]), tmp_path, x0, u, y, oc)
    assert not want.states.any() and not got.states.any()
    assert (np.signbit(got.states) != np.signbit(want.states)).any()     # the edge is real
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.residuals, want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


def test_columns_c_16_byte_rows(tmp_path):
    """double rows padded to 16 bytes (SSE2, NEON: 6 lanes for 6 states), vectorized at -O2."""
    system, u, y, x0, oc = nonfinite_playback()
    obs = ref.FloatObserver(system, FAULTS)
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs", layout="columns", vector_bytes=16)
    assert "#define OBS_W 6 " in src.header
    got = gcc_run(src, gcc_build(src, tmp_path, "-O2"), tmp_path, x0, u, y, oc)
    assert same_up_to_zero_sign(got.states, want.states)
    assert np.array_equal(got.in_use, want.in_use)


def test_columns_source():
    """The column layout reads each nonzero column of [Phi B0 B1] and of every gain once
    (rows padded to 32 bytes); the supervision is the rows layout's, line for line; fixed
    point is rows only."""
    system, *_ = playback(10)
    for dtype, lanes in ((np.float32, 8), (np.float64, 4)):
        obs = ref.FloatObserver(system, FAULTS, dtype=dtype)
        src = ref.generate_c(obs, "obs", layout="columns")
        rows = ref.generate_c(obs, "obs")
        W = -(-system.n_states // lanes) * lanes
        K = int(np.any(np.hstack([system.Phi, system.B0, system.B1]) != 0, axis=0).sum() +
                sum(np.any(L != 0, axis=0).sum() for L in system.gain_table))
        assert f"#define OBS_W {W}" in src.header and f"obs_x[OBS_W]" in src.header
        assert f"OBS_COLS[{K}][OBS_W]" in src.source
        step = src.source[src.source.index("uint8_t obs_step("):]
        supervision = rows.source[rows.source.index("/* channel 0"):
                                  rows.source.index("    switch (mask)")]
        assert supervision in step
    fx = ref.FixedObserver(system, "q16.16", IMU6_SCALING["q16.16"])
    with pytest.raises(ValueError, match="layout"):
        ref.generate_c(fx, "obs", layout="columns")
    with pytest.raises(ValueError, match="layout"):
        ref.generate_c(obs, "obs", layout="diagonal")
    with pytest.raises(ValueError, match="vector_bytes"):
        ref.generate_c(obs, "obs", layout="columns", vector_bytes=12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_columns_c_with_bias_channels(artifact, dtype, tmp_path):
    """With bias channels (evaluated in double from the corrected state), vectorized."""
    flags = AVX2 if cpu_has_x86_64_v3(tmp_path) else FLAGS[1]
    u, y, x0, oc = faulted(24_000)
    obs = ref.FloatObserver(artifact.system, BIAS_FAULTS, dtype=dtype,
                            biases=artifact.bias_evaluator())
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs", names=artifact.names, layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y, oc)
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.bias, want.bias)
    assert np.array_equal(got.in_use, want.in_use)
