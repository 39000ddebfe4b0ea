"""Discretization accuracy and speed: thermojax vs scipy cont2discrete vs control.sample_system.

Model: the six-node IMU network (configs/imu6.toml), time constants ~0.1 s to ~300 s,
sampled at dt = 0.01, 0.1, 1, 10, 60 s. Every method starts from the same float64
`A, B, C, D` (from `ThermalNetwork.linear_system()`).

Reference: the augmented-matrix exponential `expm([[A dt, B dt, 0], [0, 0, I], [0, 0, 0]])`
evaluated by mpmath at 50 significant digits from the exact values of those float64
entries (and of the float64 dt). Its blocks are `E11 = e^(A dt)` (Ad), `E12` (the ZOH
input matrix) and `E13` (the ramp integral used by first-order hold).

Accuracy = relative 2-norm error `||M - M_ref||_2 / ||M_ref||_2` of:

- `Ad` for every method;
- `Bd` for zero-order hold (thermojax: `B0` of the system with both inputs on "zoh");
- first-order hold. The tools use different state coordinates: thermojax keeps the
  physical state, `x[k+1] = Ad x[k] + B0 u[k] + B1 u[k+1]` with `B0 = E12 - E13`,
  `B1 = E13`; scipy (and control, which calls scipy) use `xi = x - E13 u`, giving
  `xi[k+1] = Ad xi[k] + Bd u[k]`, `y = C xi + Dd u` with `Bd = E12 - E13 + E11 E13`,
  `Dd = D + C E13`. Both describe the same input-output map. thermojax's `B0`, `B1` are
  compared with their references, and every tool's `Bd`, `Dd` with theirs (thermojax's
  converted as `Bd = B0 + Ad B1`, `Dd = D + C B1`, a float64 product that adds ~1e-16).

Timing: one call (thermojax jitted, after compile, best of many calls; scipy and control
called directly), and a batch of 1000 dt values in 0.01..60 s (thermojax `jax.vmap` in
one jitted call vs a Python loop of scipy / control calls).

Usage:  python benchmarks/discretize.py [--calls 300] [--batch 1000]

BLAS threads: the script sets `OPENBLAS_NUM_THREADS=1` (unless already set) before NumPy
loads. On this shared 2-core machine OpenBLAS's thread hand-offs made scipy's 8x8 `expm`
take ~16 ms per call instead of ~20 us whenever other processes were running; one thread
is the fast setting for every tool here (jaxlib's LAPACK calls go through the same
OpenBLAS).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import control  # noqa: E402
import mpmath as mp  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
from scipy.signal import cont2discrete  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import thermojax as tj  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DTS = (0.01, 0.1, 1.0, 10.0, 60.0)


def mp_reference(A, B, dt, dps=50):
    """E11, E12, E13 of the augmented exponential, as mpmath matrices (dps digits)."""
    n, m = B.shape
    with mp.workdps(dps):
        M = mp.zeros(n + 2 * m, n + 2 * m)
        h = mp.mpf(float(dt))
        for i in range(n):
            for j in range(n):
                M[i, j] = mp.mpf(float(A[i, j])) * h
            for j in range(m):
                M[i, n + j] = mp.mpf(float(B[i, j])) * h
        for j in range(m):
            M[n + j, n + m + j] = mp.mpf(1)
        E = mp.expm(M)
        return (E[:n, :n], E[:n, n:n + m], E[:n, n + m:n + 2 * m])


def rel_err(M, ref, dps=50):
    """||M - ref||_2 / ||ref||_2, the difference taken in mpmath, norms in float64."""
    M = np.asarray(M, dtype=float)
    with mp.workdps(dps):
        diff = np.array([[float(mp.mpf(float(M[i, j])) - ref[i, j]) for j in range(M.shape[1])]
                         for i in range(M.shape[0])])
        refv = np.array([[float(ref[i, j]) for j in range(M.shape[1])]
                         for i in range(M.shape[0])])
    return np.linalg.norm(diff, 2) / np.linalg.norm(refv, 2)


def mp_mat(x):
    return mp.matrix([[mp.mpf(float(v)) for v in row] for row in np.atleast_2d(np.asarray(x))])


def per_call(fn, calls):
    """Best and median seconds per call over `calls` timed calls (after one warm-up)."""
    fn()
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), float(np.median(times))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=300, help="timed calls per single-call figure")
    ap.add_argument("--batch", type=int, default=1000, help="dt values in the batch timing")
    args = ap.parse_args()
    warnings.simplefilter("ignore", category=DeprecationWarning)

    print(f"thermojax discretize benchmark: imu6, dt in {DTS} s")
    print(f"jax {jax.__version__} ({jax.default_backend()}), scipy {scipy.__version__}, "
          f"control {control.__version__}, mpmath {mp.__version__}; "
          f"OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}; "
          f"load average at start {os.getloadavg()[0]:.1f}")

    network = tj.ThermalNetwork.from_spec(tj.load_model(ROOT / "configs" / "imu6.toml"))
    sys_mixed = network.linear_system()  # T_chamber foh, P_asic zoh
    sys_zoh = tj.LinearSystem(sys_mixed.A, sys_mixed.B, sys_mixed.C, sys_mixed.D,
                              holds=("zoh", "zoh"), capacitance=sys_mixed.capacitance)
    sys_foh = tj.LinearSystem(sys_mixed.A, sys_mixed.B, sys_mixed.C, sys_mixed.D,
                              holds=("foh", "foh"), capacitance=sys_mixed.capacitance)
    A, B, C, D = (np.asarray(x) for x in (sys_mixed.A, sys_mixed.B, sys_mixed.C, sys_mixed.D))
    ss = control.ss(A, B, C, D)
    tau = np.asarray(network.time_constants())
    print(f"time constants {tau.min():.3g} .. {tau.max():.3g} s; "
          f"||A dt||_1 = {np.linalg.norm(A, 1) * DTS[0]:.3g} .. "
          f"{np.linalg.norm(A, 1) * DTS[-1]:.3g}")

    disc_jit = jax.jit(lambda s, dt: tj.discretize(s, dt))
    modal_jit = jax.jit(lambda s, dt: tj.discretize(s, dt, tj.Modal()))

    # --- accuracy ---------------------------------------------------------------------------
    t0 = time.perf_counter()
    refs = {dt: mp_reference(A, B, dt) for dt in DTS}
    print(f"mpmath references (dps 50) in {time.perf_counter() - t0:.1f} s")
    rows: dict[str, list[float]] = {}

    def add(name, value):
        rows.setdefault(name, []).append(value)

    for dt in DTS:
        E11, E12, E13 = refs[dt]
        with mp.workdps(50):
            bd_ref = E12 - E13 + E11 * E13
            dd_ref = mp_mat(D) + mp_mat(C) * E13
            b0_ref = E12 - E13
        jz = disc_jit(sys_zoh, dt)
        jf = disc_jit(sys_foh, dt)
        mz = modal_jit(sys_zoh, dt)
        mf = modal_jit(sys_foh, dt)
        sz = cont2discrete((A, B, C, D), dt, method="zoh")
        sf = cont2discrete((A, B, C, D), dt, method="foh")
        cz = control.sample_system(ss, dt, method="zoh")
        cf = control.sample_system(ss, dt, method="foh")

        add("Ad | thermojax MatrixExponential", rel_err(jf.Phi, E11))
        add("Ad | thermojax Modal", rel_err(mf.Phi, E11))
        add("Ad | scipy cont2discrete zoh", rel_err(sz[0], E11))
        add("Ad | scipy cont2discrete foh", rel_err(sf[0], E11))
        add("Ad | control.sample_system zoh", rel_err(cz.A, E11))
        add("Ad | control.sample_system foh", rel_err(cf.A, E11))
        add("zoh Bd | thermojax MatrixExponential", rel_err(jz.B0, E12))
        add("zoh Bd | thermojax Modal", rel_err(mz.B0, E12))
        add("zoh Bd | scipy cont2discrete", rel_err(sz[1], E12))
        add("zoh Bd | control.sample_system", rel_err(cz.B, E12))
        add("foh B0 = E12-E13 | thermojax MatrixExponential", rel_err(jf.B0, b0_ref))
        add("foh B0 = E12-E13 | thermojax Modal", rel_err(mf.B0, b0_ref))
        add("foh B1 = E13 | thermojax MatrixExponential", rel_err(jf.B1, E13))
        add("foh B1 = E13 | thermojax Modal", rel_err(mf.B1, E13))
        phi, b0, b1 = (np.asarray(x) for x in (jf.Phi, jf.B0, jf.B1))
        add("foh Bd (scipy coords) | thermojax MatExp, converted", rel_err(b0 + phi @ b1, bd_ref))
        add("foh Bd (scipy coords) | scipy cont2discrete", rel_err(sf[1], bd_ref))
        add("foh Bd (scipy coords) | control.sample_system", rel_err(cf.B, bd_ref))
        add("foh Dd = D + C E13 | thermojax MatExp, converted", rel_err(D + C @ b1, dd_ref))
        add("foh Dd = D + C E13 | scipy cont2discrete", rel_err(sf[3], dd_ref))
        add("foh Dd = D + C E13 | control.sample_system", rel_err(cf.D, dd_ref))

    print()
    print("Accuracy: relative 2-norm error vs mpmath (dps 50)")
    head = f"{'matrix | method':<52}" + "".join(f"{'dt=' + format(dt, 'g'):>10}" for dt in DTS)
    print(head)
    print("-" * len(head))
    group = None
    for name, vals in rows.items():
        g = name.split(" | ")[0]
        if group is not None and g != group:
            print()
        group = g
        print(f"{name:<52}" + "".join(f"{v:>10.1e}" for v in vals))

    # --- time per call ------------------------------------------------------------------------
    dt = 0.1
    dt_dev = jnp.asarray(dt)
    timings = [
        ("thermojax MatrixExponential, jit (imu6 foh+zoh)",
         lambda: jax.block_until_ready(disc_jit(sys_mixed, dt_dev))),
        ("thermojax MatrixExponential, jit (zoh)",
         lambda: jax.block_until_ready(disc_jit(sys_zoh, dt_dev))),
        ("thermojax MatrixExponential, jit (foh)",
         lambda: jax.block_until_ready(disc_jit(sys_foh, dt_dev))),
        ("thermojax Modal, jit (foh)",
         lambda: jax.block_until_ready(modal_jit(sys_foh, dt_dev))),
        ("scipy cont2discrete zoh", lambda: cont2discrete((A, B, C, D), dt, method="zoh")),
        ("scipy cont2discrete foh", lambda: cont2discrete((A, B, C, D), dt, method="foh")),
        ("control.sample_system zoh", lambda: control.sample_system(ss, dt, method="zoh")),
        ("control.sample_system foh", lambda: control.sample_system(ss, dt, method="foh")),
    ]
    print()
    print(f"Time per call at dt = {dt} s ({args.calls} calls; thermojax after compile)")
    print(f"{'method':<52}{'best (us)':>12}{'median (us)':>14}")
    print("-" * 78)
    for name, fn in timings:
        best, med = per_call(fn, args.calls)
        print(f"{name:<52}{best * 1e6:>12.1f}{med * 1e6:>14.1f}")

    # --- batch of dt values ---------------------------------------------------------------------
    dts = np.geomspace(0.01, 60.0, args.batch)
    batch = {}
    for label, system, method in (("zoh", sys_zoh, "zoh"), ("foh", sys_foh, "foh")):
        vm = jax.jit(jax.vmap(lambda d, s=system: tj.discretize(s, d)))
        dts_dev = jnp.asarray(dts)
        t0 = time.perf_counter()
        compiled = vm.lower(dts_dev).compile()
        compile_s = time.perf_counter() - t0
        jax_s, _ = per_call(lambda: jax.block_until_ready(compiled(dts_dev)), 20)
        out = compiled(dts_dev)
        # spot check the batch against single calls
        for k in (0, args.batch // 2, args.batch - 1):
            one = disc_jit(system, dts[k])
            assert np.allclose(out.Phi[k], one.Phi, rtol=1e-13, atol=1e-15)
            assert np.allclose(out.B0[k], one.B0, rtol=1e-13, atol=1e-15)
        t0 = time.perf_counter()
        for d in dts:
            cont2discrete((A, B, C, D), d, method=method)
        scipy_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for d in dts:
            control.sample_system(ss, d, method=method)
        control_s = time.perf_counter() - t0
        batch[label] = (compile_s, jax_s, scipy_s, control_s)

    print()
    print(f"Batch of {args.batch} dt values in 0.01..60 s (thermojax: one jitted vmap call, "
          "best of 20, compile separate)")
    print(f"{'hold':<6}{'thermojax (ms)':>16}{'compile (s)':>13}{'scipy loop (ms)':>17}"
          f"{'control loop (ms)':>19}{'vs scipy':>10}{'vs control':>12}")
    print("-" * 93)
    for label, (compile_s, jax_s, scipy_s, control_s) in batch.items():
        print(f"{label:<6}{jax_s * 1e3:>16.2f}{compile_s:>13.2f}{scipy_s * 1e3:>17.1f}"
              f"{control_s * 1e3:>19.1f}{scipy_s / jax_s:>9.0f}x{control_s / jax_s:>11.0f}x")
    print(f"load average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
