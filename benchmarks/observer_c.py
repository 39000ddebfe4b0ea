"""Instructions per observer step of the generated C (valgrind callgrind, an x86-64 proxy),
static RAM, and the fixed-point error figures, for the six-node IMU at 20 Hz.

    python benchmarks/observer_c.py            # ~1 min: callgrind + 24 h C playbacks
    python benchmarks/observer_c.py --numpy-24h   # also the 24 h NumPy fixed-point runs (~4 min)

Float builds are counted in both layouts of `generate_c`: `rows` (straight-line, the
default) and `columns` (column-at-a-time sums over rows padded to 32 bytes, AVX2; double
also padded to 16 bytes, SSE2; the channel supervision lane-parallel, `supervision="lanes"`,
unless marked "in branches"). The observer's supervision is the default `FaultConfig`
(plausibility, open circuit, recovery); the builds marked "full supervision" add a
residual threshold of 0.5 K (wire-break test, bad-run counter) and ADC rails inside the
plausible range on one channel.

Needs gcc, valgrind and the dev extras (scipy). The observer (3 sensors, 2 inputs) uses
Kalman gains for every sensor subset, built as in `tests/test_reference_setup.py`.
"""

import argparse
import pathlib
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_reference_setup import (IMU6_SCALING, fault_free_observer, playback)  # noqa: E402

import thermojax.reference as ref  # noqa: E402

SEED_TABLE = [("Cortex-M4F 168 MHz", "float32", 4820, 384),
              ("Cortex-M7 400 MHz", "float64", 2150, 768),
              ("TI C6748 DSP", "float32 SIMD", 980, 512),
              ("RV32IMAC 100 MHz", "Q8.24 emulated", 14600, 256)]


def compile_and_count(src, folder, flags, x0, u, y):
    paths = src.write(folder)
    obj = folder / f"{src.prefix}.o"
    exe = folder / f"{src.prefix}_prog"
    base = ["gcc", "-std=c99", "-ffp-contract=off", *flags]
    subprocess.run(base + ["-c", "-o", str(obj), str(paths["source"])], check=True)
    subprocess.run(base + ["-o", str(exe), str(obj), str(paths["harness"]), "-lm"], check=True)
    (folder / "in.bin").write_bytes(src.pack_playback(x0, u, y))
    out = folder / "callgrind.out"
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}",
                    f"--toggle-collect={src.prefix}_step", str(exe), str(folder / "in.bin"),
                    str(folder / "out.bin")], check=True, capture_output=True)
    text = out.read_text()
    total = int(re.search(r"^(?:summary|totals):\s+(\d+)", text, re.M).group(1))
    sections = subprocess.run(["size", "-A", str(obj)], check=True, capture_output=True,
                              text=True).stdout
    sec = {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\.\S+)\s+(\d+)", sections, re.M)}
    ram = sec.get(".bss", 0) + sec.get(".data", 0)
    flash = sum(v for k, v in sec.items() if k.startswith((".rodata", ".text")))
    return total / u.shape[0], ram, flash


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--numpy-24h", action="store_true")
    args = ap.parse_args()
    for tool in ("gcc", "valgrind", "size"):
        if subprocess.run(["which", tool], capture_output=True).returncode:
            sys.exit(f"{tool} is required")
    system, u, y, _, x0 = playback(args.steps)
    n, m, p = system.n_states, system.n_inputs, system.n_outputs
    floor = n * n + n * m + n * p
    dense = n * n + 2 * n * m + p * n + p * m + n * p
    nz = int(sum(np.count_nonzero(M) for M in (system.Phi, system.B0, system.B1, system.C,
                                              system.D, system.L)))
    print(f"imu6 at 20 Hz: n={n} states, m={m} inputs, p={p} sensors")
    print(f"MAC floor n^2+n*m+n*p = {floor}; dense MACs of the FOH equations "
          f"(Phi, B0, B1, C, D, L) = {dense}; structurally nonzero = {nz}")
    f32, f64 = ref.FloatObserver(system, dtype=np.float32), ref.FloatObserver(system)
    builds = {"float (float32)": (f32, "rows", 32), "double (float64)": (f64, "rows", 32),
              "Q16.16": (ref.FixedObserver(system, "q16.16", IMU6_SCALING["q16.16"]), "rows", 32),
              "Q8.24": (ref.FixedObserver(system, "q8.24", IMU6_SCALING["q8.24"]), "rows", 32),
              "Q15": (ref.FixedObserver(system, "q15", IMU6_SCALING["q15"]), "rows", 32),
              "float (float32), columns": (f32, "columns", 32),
              "double (float64), columns": (f64, "columns", 32),
              "double (float64), columns, 16-byte rows": (f64, "columns", 16)}
    full = ref.FaultConfig(rails=[(-np.inf, np.inf)] * (p - 1) + [(-40.0, 100.0)],
                           residual_threshold=0.5)
    for dtype, name in ((np.float32, "float (float32)"), (np.float64, "double (float64)")):
        obs = ref.FloatObserver(system, full, dtype=dtype)
        builds[f"{name}, full supervision"] = (obs, "rows", 32)
        builds[f"{name}, columns, full supervision"] = (obs, "columns", 32)
        builds[f"{name}, columns, full supervision in branches"] = (obs, "columns", 32,
                                                                    "branches")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for flags in (["-O2"], ["-O3", "-march=x86-64-v3"]):
            for name, (obs, layout, vector_bytes, *supervision) in builds.items():
                src = ref.generate_c(obs, "obs", layout=layout, vector_bytes=vector_bytes,
                                     supervision=(supervision or [None])[0])
                if isinstance(obs, ref.FixedObserver):
                    data = (obs.encode_states(x0), obs.encode_inputs(u), obs.encode_outputs(y))
                else:
                    data = (x0, u, y)
                folder = pathlib.Path(tmp) / re.sub(r"\W", "_", name + "".join(flags))
                folder.mkdir()
                ipc, ram, flash = compile_and_count(src, folder, flags, *data)
                rows.append((name, " ".join(flags), ipc, ram, flash))
    print("\n| build | gcc flags | instructions/step | / MAC floor (66) | / dense MACs (102) "
          "| static RAM (B) | flash: code+const (B) |")
    print("|---|---|---|---|---|---|---|")
    for name, flags, ipc, ram, flash in rows:
        print(f"| {name} | {flags} | {ipc:.0f} | {ipc / floor:.2f} | {ipc / dense:.2f} "
              f"| {ram} | {flash} |")
    print("\nseed's processor table (cycles/step, RAM bytes), for comparison:")
    for row in SEED_TABLE:
        print(f"  {row[0]:<22} {row[1]:<16} {row[2]:>6} cycles  {row[3]:>4} B")

    # -- fixed-point error over 24 h at 20 Hz, by the generated C (bit-exact with NumPy) ---
    print("\n24 h playback at 20 Hz (1,728,000 steps): max |fixed - float64| per state (K)")
    sysb, U, Y, _, X0 = playback(1_728_000, seed=3)
    x64 = fault_free_observer(sysb, X0, U, Y)
    r64 = Y - x64 @ sysb.C.T
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in ("q16.16", "q8.24", "q15"):
            fx = ref.FixedObserver(sysb, fmt, IMU6_SCALING[fmt])
            src = ref.generate_c(fx, "obs")
            folder = pathlib.Path(tmp)
            paths = src.write(folder)
            exe = folder / "prog"
            subprocess.run(["gcc", "-std=c99", "-O2", "-o", str(exe), str(paths["source"]),
                            str(paths["harness"]), "-lm"], check=True)
            (folder / "in.bin").write_bytes(src.pack_playback(
                fx.encode_states(X0), fx.encode_inputs(U), fx.encode_outputs(Y)))
            t = time.perf_counter()
            subprocess.run([str(exe), str(folder / "in.bin"), str(folder / "out.bin")], check=True)
            t = time.perf_counter() - t
            out = src.unpack_output((folder / "out.bin").read_bytes())
            xs = fx.decode_states(out.states)
            err = np.abs(xs - x64)
            x_env = np.abs(x64 - fx.x_ref).max(0) + 0.5
            b = ref.quantization_error_bound(fx, x_env, x_env + 0.5,
                                             np.abs(U - fx.u_ref).max(0),
                                             np.abs(r64).max(0) + 0.5)
            bias = (xs - x64)[-72_000:].mean(0)
            print(f"  {fmt:7s} C run {t:.2f} s; J={b.J}")
            print(f"    measured max : {np.array2string(err.max(0), precision=3)}")
            print(f"    derived bound: {np.array2string(b.bound, precision=3)}")
            print(f"    bound parts  : " + ", ".join(f"{k} {v.max():.3g}" for k, v in b.parts.items()))
            print(f"    mean error, last hour: {np.array2string(bias, precision=3)}")
            if fmt == "q15":
                lost = (fx.coef["Phi"] == 0) & (sysb.Phi != 0)
                print(f"    Phi entries zeroed in Q15: {int(lost.sum())} of "
                      f"{int(np.count_nonzero(sysb.Phi))}; largest "
                      f"{np.abs(sysb.Phi[lost]).max():.2e}")
                # coefficient effect alone: float64 observer with the Q15 coefficients
                q = {k: fx.coef[k] * 2.0 ** -fx.coef_frac[k] for k in ("Phi", "C", "L")}
                qsys = ref.ObserverSystem.build(q["Phi"], sysb.B0 + fx.coef_error["B0"],
                                                sysb.B1 + fx.coef_error["B1"], q["C"], sysb.D,
                                                {(0, 1, 2): q["L"][7], **{
                                                    s: sysb.gain(s)[:, list(s)] for s in
                                                    [(0,), (1,), (2,), (0, 1), (0, 2), (1, 2)]}})
                xq = fault_free_observer(qsys, X0, U, Y)
                print(f"    float64 with Q15 coefficients only: max "
                      f"{np.array2string(np.abs(xq - x64).max(0), precision=3)}")
    if args.numpy_24h:
        for fmt in ("q16.16", "q8.24"):
            fx = ref.FixedObserver(sysb, fmt, IMU6_SCALING[fmt])
            t = time.perf_counter()
            run = fx.run_physical(X0, U, Y)
            print(f"  NumPy {fmt} 24 h: {time.perf_counter() - t:.0f} s, max error "
                  f"{np.abs(run.states - x64).max():.3g} K")


if __name__ == "__main__":
    main()
