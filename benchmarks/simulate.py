"""Batch simulation throughput: thermojax vs scipy.signal.dlsim vs a vectorized NumPy loop.

256 thermal-chamber profiles x 4 h at Ts = 0.1 s (144,000 samples each) through the
six-node IMU model (configs/imu6.toml; T_chamber first-order hold, P_asic zero-order hold).
All three tools get the same inputs, the same initial states (the steady state at the
first sample) and the same discrete matrices (thermojax's exact `MatrixExponential`
discretization, Phi, B0, B1):

- thermojax: `jax.jit(jax.vmap(simulate(...).outputs))`, compile timed separately,
  steady-state time = best of `--repeats` calls;
- NumPy: one Python loop over time, vectorized over the profiles,
  `X = X @ Phi.T + U[k] @ B0.T + U[k+1] @ B1.T`, outputs written time-major;
- scipy.signal.dlsim: one call per profile, ZOH form with the augmented input
  `[u_k, u_(k+1)]` and `B = [B0 B1]`; only `--dlsim-profiles` profiles are timed and
  the time is extrapolated per unit-step.

All outputs are checked against each other (1e-9 relative) before any timing. Unit-steps
= profiles x samples. The memory-bandwidth floor is the time this machine takes to write
the 885 MB output array once (NumPy fill of a warm buffer).

Usage:  python benchmarks/simulate.py [--profiles 256] [--hours 4] [--repeats 5]
                                      [--dlsim-profiles 4] [--scan-repeats 2] [--no-hugepages]

For reference it also times the step-by-step `lax.scan` that `ExactHold` used before
(same jit + vmap, on the first `--scan-hours 1` of every profile, extrapolated per
unit-step: at full length it would hold ~8 GB; `--scan-repeats 0` skips it).

Memory: ~5 GB at peak (measured max RSS; inputs 0.6 GB twice, outputs 0.9 GB per tool,
XLA temporaries).

Huge pages: on this (virtualized) machine a 4 KiB page fault costs ~4 us, so any fresh
885 MB buffer costs ~0.9 s to touch. NumPy asks the kernel for transparent huge pages on
its large arrays (madvise); XLA's allocator does not. To compare the tools on equal
allocator terms the script re-executes itself with `GLIBC_TUNABLES=glibc.malloc.hugetlb=1`
(glibc >= 2.35: malloc then madvises huge pages too). `--no-hugepages` runs with the
default allocator instead; see benchmarks/README.md for both.

BLAS threads: `OPENBLAS_NUM_THREADS=1` unless already set. The NumPy loop's 256x6 @ 6x6
products gain nothing from threads, and on this shared 2-core machine OpenBLAS's thread
hand-offs slow it down (1.3-1.4x here); one thread is NumPy's and dlsim's best setting.
XLA does not use OpenBLAS for its matrix products.
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if "--no-hugepages" not in sys.argv and \
        "glibc.malloc.hugetlb" not in os.environ.get("GLIBC_TUNABLES", ""):
    _env = dict(os.environ)
    _env["GLIBC_TUNABLES"] = ":".join(
        t for t in (os.environ.get("GLIBC_TUNABLES", ""), "glibc.malloc.hugetlb=1") if t)
    os.execve(sys.executable, [sys.executable, *sys.argv], _env)

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.signal  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import thermojax as tj  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DT = 0.1


def make_profiles(n_profiles: int, n_samples: int, seed: int = 0) -> np.ndarray:
    """(profiles, samples, 2): chamber temperature (°C) and ASIC power (W).

    Chamber: plateaus of 5-40 min at random levels in -40..85 °C joined by ramps at
    1-10 °C/min (piecewise linear). Power: steps between random levels in 0.05-0.4 W
    every 1-30 min (piecewise constant).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) * DT
    out = np.empty((n_profiles, n_samples, 2))
    for i in range(n_profiles):
        bt, bv = [0.0], [rng.uniform(-40.0, 85.0)]
        while bt[-1] < t[-1]:
            bt.append(bt[-1] + rng.uniform(300.0, 2400.0))
            bv.append(bv[-1])
            level = rng.uniform(-40.0, 85.0)
            rate = rng.uniform(1.0, 10.0) / 60.0  # °C/s
            bt.append(bt[-1] + max(abs(level - bv[-1]) / rate, DT))
            bv.append(level)
        out[i, :, 0] = np.interp(t, bt, bv)
        switch = np.cumsum(rng.uniform(60.0, 1800.0, size=int(t[-1] / 60.0) + 2))
        levels = rng.uniform(0.05, 0.4, size=switch.size + 1)
        out[i, :, 1] = levels[np.searchsorted(switch, t, side="right")]
    return out


class StepScan(tj.AbstractSimulator):
    """The step-by-step `lax.scan` that `ExactHold` ran before it was blocked (for reference)."""

    def run(self, system, x0, inputs, ts):
        disc = tj.discretize(system, ts[1] - ts[0])
        drive = inputs[:-1] @ disc.B0.T + inputs[1:] @ disc.B1.T

        def step(x, b):
            x = disc.Phi @ x + b
            return x, x

        _, rest = jax.lax.scan(step, x0, drive, unroll=8)
        states = jnp.concatenate([x0[None, :], rest], axis=0)
        return tj.Solution(ts, states, states @ disc.C.T + inputs @ disc.D.T)


def numpy_loop(Phi, B0, B1, C, D, x0s, U):
    """Time loop vectorized over profiles; returns outputs (samples, profiles, outputs)."""
    n_profiles, n_samples, _ = U.shape
    Ut = np.ascontiguousarray(U.transpose(1, 0, 2))
    PhiT, B0T, B1T, CT, DT_ = Phi.T.copy(), B0.T.copy(), B1.T.copy(), C.T.copy(), D.T.copy()
    Y = np.empty((n_samples, n_profiles, C.shape[0]))
    X = x0s.copy()
    if not D.any():  # imu6: no feedthrough, so no `U[k] @ D.T` term per step
        for k in range(n_samples - 1):
            Y[k] = X @ CT
            X = X @ PhiT + Ut[k] @ B0T + Ut[k + 1] @ B1T
        Y[-1] = X @ CT
        return Y
    for k in range(n_samples - 1):
        Y[k] = X @ CT + Ut[k] @ DT_
        X = X @ PhiT + Ut[k] @ B0T + Ut[k + 1] @ B1T
    Y[-1] = X @ CT + Ut[-1] @ DT_
    return Y


def dlsim_one(Phi, B0, B1, C, D, x0, u):
    """scipy.signal.dlsim on the equivalent ZOH system with input [u_k, u_(k+1)]."""
    u_aug = np.concatenate([u, np.concatenate([u[1:], u[-1:]])], axis=1)
    system = (Phi, np.concatenate([B0, B1], axis=1), C,
              np.concatenate([D, np.zeros_like(D)], axis=1), DT)
    _, y, _ = scipy.signal.dlsim(system, u_aug, x0=x0)
    return y


def best_of(fn, repeats):
    """(best wall s, best process CPU s, last result) over `repeats` calls."""
    best_wall, best_cpu, result = np.inf, np.inf, None
    for _ in range(repeats):
        result = None  # free the previous output before the next call allocates its own
        c0, t0 = time.process_time(), time.perf_counter()
        result = jax.block_until_ready(fn())
        best_wall = min(best_wall, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best_wall, best_cpu, result


def write_bandwidth(nbytes, repeats=5):
    """Best time to write `nbytes` (warm buffer fill) and to copy them (copyto), in s."""
    a = np.empty(nbytes // 8)
    b = np.empty_like(a)
    a.fill(1.0)
    b.fill(2.0)
    fill = min(_timed(lambda: a.fill(3.0)) for _ in range(repeats))
    copy = min(_timed(lambda: np.copyto(b, a)) for _ in range(repeats))
    fresh = min(_timed(lambda: np.full(nbytes // 8, 1.0)) for _ in range(repeats))
    return fill, copy, fresh


def _timed(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def rel_diff(a, b):
    """max |a - b| / max |b|, over leading-axis chunks (no full-size temporaries)."""
    a, b = np.asarray(a), np.asarray(b)
    chunk = max(1, 4_000_000 // max(1, a[0].size))
    num = max(float(np.max(np.abs(a[i:i + chunk] - b[i:i + chunk])))
              for i in range(0, a.shape[0], chunk))
    return num / float(np.max(np.abs(b)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--profiles", type=int, default=256)
    ap.add_argument("--hours", type=float, default=4.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--numpy-repeats", type=int, default=3)
    ap.add_argument("--dlsim-profiles", type=int, default=4)
    ap.add_argument("--scan-repeats", type=int, default=2,
                    help="time the old step-by-step lax.scan too (0: skip)")
    ap.add_argument("--scan-hours", type=float, default=1.0,
                    help="horizon the old scan is timed on (extrapolated per unit-step)")
    ap.add_argument("--no-hugepages", action="store_true")
    args = ap.parse_args()

    n_samples = int(round(args.hours * 3600 / DT))
    n_prof = args.profiles
    units = n_prof * n_samples
    print(f"thermojax simulate benchmark: {n_prof} profiles x {n_samples} samples "
          f"(Ts = {DT} s, {args.hours:g} h) = {units:,} unit-steps")
    hugepages = "on" if "hugetlb" in os.environ.get("GLIBC_TUNABLES", "") else "off"
    print(f"machine: {os.cpu_count()} CPUs, jax {jax.__version__} on {jax.default_backend()}, "
          f"numpy {np.__version__}, scipy {scipy.__version__}; malloc huge pages: {hugepages}; "
          f"OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}; "
          f"load average at start {os.getloadavg()[0]:.1f}")

    network = tj.ThermalNetwork.from_spec(tj.load_model(ROOT / "configs" / "imu6.toml"))
    system = network.linear_system()
    disc = tj.discretize(system, DT)
    Phi, B0, B1, C, D = (np.asarray(m) for m in (disc.Phi, disc.B0, disc.B1, disc.C, disc.D))
    A, B = np.asarray(system.A), np.asarray(system.B)

    t0 = time.perf_counter()
    U = make_profiles(n_prof, n_samples)
    print(f"profiles generated in {time.perf_counter() - t0:.1f} s "
          f"(inputs {U.nbytes / 1e6:.0f} MB, outputs {units * 3 * 8 / 1e6:.0f} MB per tool)")
    x0s = np.linalg.solve(A, -(B @ U[:, 0, :].T)).T  # steady state at the first sample

    # --- thermojax -------------------------------------------------------------------------
    ts = jnp.arange(n_samples) * DT
    U_dev = jnp.asarray(U)

    @eqx.filter_jit
    def tj_outputs(network, U, ts, simulator=tj.ExactHold()):
        return jax.vmap(lambda u: tj.simulate(network, u, ts, simulator=simulator).outputs)(U)

    t0 = time.perf_counter()
    compiled = tj_outputs.lower(network, U_dev, ts).compile()
    compile_s = time.perf_counter() - t0
    Y_tj = jax.block_until_ready(compiled(network, U_dev, ts))  # first run (touches memory)

    # --- correctness, before timing ----------------------------------------------------------
    Y_np = numpy_loop(Phi, B0, B1, C, D, x0s, U)
    err_np = rel_diff(np.asarray(Y_tj).transpose(1, 0, 2), Y_np)
    n_dl = min(args.dlsim_profiles, n_prof)
    Y_dl = [dlsim_one(Phi, B0, B1, C, D, x0s[i], U[i]) for i in range(n_dl)]
    err_dl = max(rel_diff(np.asarray(Y_tj[i]), Y_dl[i]) for i in range(n_dl))
    err_dl_np = max(rel_diff(Y_np[:, i], Y_dl[i]) for i in range(n_dl))
    print(f"agreement (max |diff| / max |y|): thermojax vs NumPy {err_np:.1e} "
          f"(all {n_prof} profiles); thermojax vs dlsim {err_dl:.1e}, NumPy vs dlsim "
          f"{err_dl_np:.1e} ({n_dl} profiles)")
    if max(err_np, err_dl, err_dl_np) > 1e-9:
        raise SystemExit("outputs disagree by more than 1e-9: not timing.")
    del Y_tj, Y_dl
    if args.scan_repeats:
        # The vmapped step-by-step scan holds drive, states and their transposes (~8 GB at
        # full length): run it on the first `--scan-hours` of every profile and
        # extrapolate per unit-step (its cost is linear in the number of samples).
        n_scan = min(n_samples, int(round(args.scan_hours * 3600 / DT)))
        U_scan, ts_scan = U_dev[:, :n_scan], ts[:n_scan]
        scan_compiled = tj_outputs.lower(network, U_scan, ts_scan, StepScan()).compile()
        Y_scan = scan_compiled(network, U_scan, ts_scan, StepScan())
        err_scan = rel_diff(np.asarray(Y_scan).transpose(1, 0, 2), Y_np[:n_scan])
        print(f"agreement: step-by-step lax.scan vs NumPy {err_scan:.1e} "
              f"(first {n_scan} samples)")
        if err_scan > 1e-9:
            raise SystemExit("outputs disagree by more than 1e-9: not timing.")
        del Y_scan
    del Y_np

    # --- timing --------------------------------------------------------------------------------
    tj_wall, tj_cpu, _ = best_of(lambda: compiled(network, U_dev, ts), args.repeats)
    if args.scan_repeats:
        scan_wall, scan_cpu, _ = best_of(
            lambda: scan_compiled(network, U_scan, ts_scan, StepScan()), args.scan_repeats)
        scan_wall, scan_cpu = scan_wall * n_samples / n_scan, scan_cpu * n_samples / n_scan
    np_wall, np_cpu, _ = best_of(lambda: numpy_loop(Phi, B0, B1, C, D, x0s, U),
                                 args.numpy_repeats)
    dl_times = []
    for i in range(n_dl):
        t0 = time.perf_counter()
        dlsim_one(Phi, B0, B1, C, D, x0s[i], U[i])
        dl_times.append(time.perf_counter() - t0)
    dl_per_unit = sum(dl_times) / (n_dl * n_samples)
    dl_wall = dl_per_unit * units  # extrapolated to all profiles
    del U, U_dev  # before the bandwidth test's 2.7 GB

    fill_s, copy_s, fresh_s = write_bandwidth(units * 3 * 8)
    out_gb = units * 3 * 8 / 1e9

    rate = lambda s: units / s  # noqa: E731
    print()
    print(f"{'tool':<48} {'time (s)':>10} {'unit-steps/s':>14} {'thermojax is':>13}")
    print("-" * 88)
    rows = [
        ("thermojax  jit(vmap(simulate)), best of %d" % args.repeats, tj_wall),
        ("NumPy loop over time, vectorized, best of %d" % args.numpy_repeats, np_wall),
        ("scipy.signal.dlsim loop (%d profiles, extrap.)" % n_dl, dl_wall),
    ]
    if args.scan_repeats:
        rows.append(("(old ExactHold, lax.scan/step, %gh extrap.)" % args.scan_hours,
                     scan_wall))
    for name, s in rows:
        print(f"{name:<48} {s:>10.3f} {rate(s):>14.3e} {s / tj_wall:>12.1f}x")
    print("-" * 88)
    print(f"thermojax compile (lower + compile, once): {compile_s:.2f} s")
    print(f"process CPU time per call (all threads): thermojax {tj_cpu:.2f} s, "
          f"NumPy {np_cpu:.2f} s "
          f"({np_cpu / tj_cpu:.1f}x)" + (f", step-by-step scan {scan_cpu:.2f} s"
                                         if args.scan_repeats else ""))
    print(f"targets: >= 50x dlsim: {'met' if dl_wall / tj_wall >= 50 else 'MISSED'} "
          f"({dl_wall / tj_wall:.0f}x); >= 3x NumPy: "
          f"{'met' if np_wall / tj_wall >= 3 else 'MISSED'} ({np_wall / tj_wall:.2f}x)")
    print()
    print(f"memory-bandwidth floor for writing the outputs ({out_gb * 1e3:.0f} MB float64):")
    print(f"  NumPy fill of a warm buffer  {fill_s:.3f} s  ({out_gb / fill_s:5.1f} GB/s)  "
          f"-> thermojax is {tj_wall / fill_s:.1f}x the floor")
    print(f"  NumPy copyto (read + write)  {copy_s:.3f} s  ({2 * out_gb / copy_s:5.1f} GB/s moved)")
    print(f"  NumPy fill of a fresh buffer {fresh_s:.3f} s  (includes page faults)")
    print(f"load average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
