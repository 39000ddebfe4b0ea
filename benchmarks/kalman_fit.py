"""Kalman-fit benchmark: the four-node building fit by thermojax against SciPy (issue 10
item 3: "the four-node Kalman fit >= 20x faster than the SciPy L-BFGS-B fit to the same
optimum (first fit, compilation included, <= 15 s)").

The model: a building-like network of four nodes (wall, air, floor, roof), one sensor on
the air, sampled every 300 s for 1,700 samples (about 5.9 days). Inputs: the outdoor
temperature T_out (boundary of the wall, the roof and the air, i.e. ventilation; held
linear, foh), a switched heating power P_heat in the air (gain fixed at 1, zoh) and the
solar irradiance I_sol (W/m², foh) entering the air through windows and the roof, each
with a free aperture gain (m²). Process noise on all four nodes, truly zero on the wall
and the floor. Free: 4 capacitances, 3 links, 3 boundary conductances, 2 solar gains, the
sensor's noise, 4 process noises and the initial temperatures of the floor and the roof:
19 parameters. The data are simulated in NumPy (exact hold, Van Loan process noise);
every fitter starts from the same perturbed start.

Fitters, all on the same data, in one process:

- thermojax: `fit(spec, [Experiment(...)], likelihood="kalman")` (the Kalman stage
  from the file's values: truncated Newton with the Fisher information and exact
  gradients, the boundary check and the polish; an output-error fit first only when that
  does not converge). The first call is timed in a fresh process with the persistent compilation
  cache off (the library turns it on only from the command line; THERMOJAX_CACHE_DIR and
  JAX_COMPILATION_CACHE_DIR are removed from the environment): compilation included.
  Then fits on new noise seeds, the same structure and shapes (warm: the compiled
  programs are reused in-process).
- SciPy, the expert peer a user would write: a NumPy continuous-discrete Kalman filter
  (update before predict, every sample included, initial mean = steady state of the
  first input with the floor and roof set to their estimated initial temperatures,
  P0 = I °C², exact foh/zoh sampling from `scipy.linalg.expm` of the augmented block
  matrix, Van Loan's block exponential for the process-noise covariance, the scalar
  measurement update written out), minimised by `scipy.optimize.minimize(method=
  "L-BFGS-B")` from the same start: logs of the positive physical parameters and the
  sensor noise, the initial temperatures as they are, and the process-noise stds q >= 0
  by bounds (linear, so zero is reachable); gradients by SciPy's default finite
  differences. Its wall time is the peer time of the ratio.
- The reference optimum: Nelder-Mead from the L-BFGS-B point (timed separately, not part
  of any ratio). thermojax's optimum is also evaluated by the NumPy filter, which must
  agree with its own -log L (the same likelihood).

BLAS threads: as in benchmarks/fit.py the script re-executes itself with
`OPENBLAS_NUM_THREADS=1` (`--default-blas-threads` keeps the environment).

Usage:  python benchmarks/kalman_fit.py [--repeats 2] [--samples 1700] [--no-polish]
                                        [--polish-maxfev 8000]
                                        [--quick] [--out results.json]
"""

from __future__ import annotations

import os

import _cold_process  # beside this script

_cold_process.reexec()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
import scipy.optimize  # noqa: E402

DT = 300.0  # s
NODES = ("wall", "air", "floor", "roof")
INPUTS = ("T_out", "P_heat", "I_sol")
FOH = np.array([True, False, True])  # T_out, I_sol linear between samples; P_heat switched
AIR = 1
INIT_NODES = (2, 3)  # floor, roof: initial temperatures estimated
# (dotted thermojax name, the NumPy vector's slot, "log" | "lin" | "q")
PARAMS = (
    ("nodes.wall.capacitance", "log"), ("nodes.air.capacitance", "log"),
    ("nodes.floor.capacitance", "log"), ("nodes.roof.capacitance", "log"),
    ("links.wall-air.conductance", "log"), ("links.air-floor.conductance", "log"),
    ("links.air-roof.conductance", "log"),
    ("boundaries.wall-T_out.conductance", "log"), ("boundaries.roof-T_out.conductance", "log"),
    ("boundaries.air-T_out.conductance", "log"),
    ("heat_inputs.air-I_sol.gain", "log"), ("heat_inputs.roof-I_sol.gain", "log"),
    ("sensors.T_air.noise", "log"),
    ("runs.0.nodes.floor.initial", "lin"), ("runs.0.nodes.roof.initial", "lin"),
    ("nodes.wall.process_noise", "q"), ("nodes.air.process_noise", "q"),
    ("nodes.floor.process_noise", "q"), ("nodes.roof.process_noise", "q"),
)
NAMES = [p for p, _ in PARAMS]
KIND = np.array([k for _, k in PARAMS])
# truth and start, physical units (J/K, W/K, m², °C, °C/√s); the initial temperatures are
# offsets from the steady state of the first input (truth) or that steady state (start)
TRUTH = np.array([2e6, 5e5, 4e6, 1.5e6, 100.0, 80.0, 60.0, 50.0, 40.0, 20.0, 3.0, 4.0, 0.05,
                  2.0, -1.5, 0.0, 0.01, 0.0, 0.003])
START = np.array([1.5e6, 6e5, 3e6, 2e6, 120.0, 60.0, 50.0, 40.0, 50.0, 25.0, 2.0, 5.0, 0.1,
                  0.0, 0.0, 0.002, 0.005, 0.002, 0.002])

MODEL = """
name = "building4"
[[nodes]]
name = "wall"
capacitance = {0}
process_noise = {15}
[[nodes]]
name = "air"
capacitance = {1}
process_noise = {16}
[[nodes]]
name = "floor"
capacitance = {2}
process_noise = {17}
initial = {13}
[[nodes]]
name = "roof"
capacitance = {3}
process_noise = {18}
initial = {14}
[[links]]
between = ["wall", "air"]
conductance = {4}
[[links]]
between = ["air", "floor"]
conductance = {5}
[[links]]
between = ["air", "roof"]
conductance = {6}
[[boundaries]]
node = "wall"
input = "T_out"
conductance = {7}
[[boundaries]]
node = "roof"
input = "T_out"
conductance = {8}
[[boundaries]]
node = "air"
input = "T_out"
conductance = {9}
[[heat_inputs]]
node = "air"
input = "P_heat"
gain = {{ value = 1.0, fixed = true }}
hold = "zoh"
[[heat_inputs]]
node = "air"
input = "I_sol"
gain = {10}
[[heat_inputs]]
node = "roof"
input = "I_sol"
gain = {11}
[[sensors]]
node = "air"
column = "T_air"
noise = {12}
"""


# ---------------------------------------------------------------------------------------------
# The NumPy side: the network and the expert's Kalman filter


def matrices(p):
    """`A` (4, 4) 1/s and `B` (4, 3) of the network at physical parameters `p` (PARAMS)."""
    c = p[0:4]
    g_wa, g_af, g_ar, g_wo, g_ro, g_ao, a_air, a_roof = p[4:12]
    K = np.array([[g_wa + g_wo, -g_wa, 0.0, 0.0],
                  [-g_wa, g_wa + g_af + g_ar + g_ao, -g_af, -g_ar],
                  [0.0, -g_af, g_af, 0.0],
                  [0.0, -g_ar, 0.0, g_ar + g_ro]])
    G = np.array([[g_wo, 0.0, 0.0], [g_ao, 1.0, a_air], [0.0, 0.0, 0.0], [g_ro, 0.0, a_roof]])
    return -K / c[:, None], G / c[:, None]


def discretize(A, B, dt):
    """Exact sampling `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]`: `expm` of
    `[[A dt, B dt, 0], [0, 0, I], [0, 0, 0]]`, the `u[k+1]` term kept for foh inputs."""
    n, m = B.shape
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n], M[:n, n:n + m], M[n:n + m, n + m:] = A * dt, B * dt, np.eye(m)
    E = scipy.linalg.expm(M)
    B1 = E[:n, n + m:] * FOH
    return E[:n, :n], E[:n, n:n + m] - B1, B1


def van_loan(A, q, dt):
    """`Qd = ∫0^dt e^{As} diag(q²) e^{Aᵀs} ds` by Van Loan's block exponential."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A * dt, np.diag(q * q) * dt, A.T * dt
    F = scipy.linalg.expm(M)
    Qd = F[n:, n:].T @ F[:n, n:]
    return 0.5 * (Qd + Qd.T)


def initial_mean(A, B, u0, init):
    m = np.linalg.solve(A, -B @ u0)
    m[list(INIT_NODES)] = init
    return m


def kalman_nll(p, U, Y, dt=DT):
    """−log L of the continuous-discrete Kalman filter (update before predict, every
    sample, P0 = I °C²) at physical parameters `p`; `U` (T, 3), `Y` (T,) °C."""
    A, B = matrices(p)
    Phi, B0, B1 = discretize(A, B, dt)
    Qd = van_loan(A, p[15:19], dt)
    r = p[12] ** 2
    drive = U @ B0.T + np.concatenate([U[1:], U[-1:]]) @ B1.T
    m = initial_mean(A, B, U[0], p[13:15])
    P = np.eye(4)
    PhiT = Phi.T
    logdet = 0.0
    quad = 0.0
    for k in range(len(Y)):
        S = P[AIR, AIR] + r
        e = Y[k] - m[AIR]
        logdet += np.log(S)
        quad += e * e / S
        K = P[:, AIR] / S
        m = Phi @ (m + K * e) + drive[k]
        P = Phi @ (P - np.outer(K, P[AIR])) @ PhiT + Qd
    return 0.5 * (len(Y) * np.log(2 * np.pi) + logdet + quad)


def to_x(p):
    """Optimizer vector of physical parameters: logs, linear initial temperatures, q."""
    return np.where(KIND == "log", np.log(np.where(KIND == "log", p, 1.0)), p)


def to_p(x):
    return np.where(KIND == "log", np.exp(np.where(KIND == "log", x, 0.0)), x)


BOUNDS = [(0.0, None) if k == "q" else (None, None) for k in KIND]


# ---------------------------------------------------------------------------------------------
# Data


def inputs(n, seed=0):
    """Outdoor temperature (a daily sine plus a slow random walk), heating switched on and
    off by the hour, solar irradiance (a clipped daily sine times slow cloud cover)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    day = 2 * np.pi * t / 86400
    t_out = 5 + 6 * np.sin(day - 2.0) + 0.05 * rng.standard_normal(n).cumsum()
    p_heat = 2000.0 * (rng.random(n // 12 + 1) < 0.5).repeat(12)[:n]
    cloud = np.clip(0.6 + 0.1 * rng.standard_normal(n // 24 + 1).cumsum(), 0.1, 1.0)
    i_sol = 600.0 * np.clip(np.sin(day - np.pi / 2), 0.0, None) * cloud.repeat(24)[:n]
    return t, np.column_stack([t_out, p_heat, i_sol])


def truth_params(U):
    """TRUTH with the initial temperatures as steady state plus the offsets."""
    p = TRUTH.copy()
    A, B = matrices(p)
    p[13:15] = np.linalg.solve(A, -B @ U[0])[list(INIT_NODES)] + TRUTH[13:15]
    return p


def start_params(U):
    p = START.copy()
    A, B = matrices(p)
    p[13:15] = np.linalg.solve(A, -B @ U[0])[list(INIT_NODES)]
    return p


def measurements(U, seed):
    """The air temperature of the network at the truth with process noise and sensor
    noise drawn from `seed` (exact hold, Van Loan)."""
    rng = np.random.default_rng(1000 + seed)
    p = truth_params(U)
    A, B = matrices(p)
    Phi, B0, B1 = discretize(A, B, DT)
    L = np.linalg.cholesky(van_loan(A, p[15:19], DT) + 1e-30 * np.eye(4))
    x = initial_mean(A, B, U[0], p[13:15])
    n = len(U)
    Y = np.empty(n)
    for k in range(n):
        Y[k] = x[AIR] + p[12] * rng.standard_normal()
        u_next = U[k + 1] if k + 1 < n else U[k]
        x = Phi @ x + B0 @ U[k] + B1 @ u_next + L @ rng.standard_normal(4)
    return Y


# ---------------------------------------------------------------------------------------------


def scipy_fit(U, Y, p_start, polish, polish_maxfev=8000):
    f = lambda x: kalman_nll(to_p(x), U, Y)  # noqa: E731
    t = time.perf_counter()
    res = scipy.optimize.minimize(f, to_x(p_start), method="L-BFGS-B", bounds=BOUNDS,
                                  options=dict(maxiter=2000))
    wall = time.perf_counter() - t
    out = dict(wall=wall, nll=float(res.fun), nfev=int(res.nfev), nit=int(res.nit),
               message=str(res.message), success=bool(res.success), p=to_p(res.x))
    if polish:
        t = time.perf_counter()
        ref = scipy.optimize.minimize(f, res.x, method="Nelder-Mead", bounds=BOUNDS,
                                      options=dict(maxiter=polish_maxfev, maxfev=polish_maxfev, xatol=1e-8,
                                                   fatol=1e-9, adaptive=True))
        out.update(ref_wall=time.perf_counter() - t, ref_nll=float(min(ref.fun, res.fun)),
                   ref_nfev=int(ref.nfev), ref_message=str(ref.message), ref_p=to_p(ref.x))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=1700, help="samples at 300 s")
    ap.add_argument("--repeats", type=int, default=2,
                    help="warm thermojax fits on new noise seeds after the first")
    ap.add_argument("--no-polish", action="store_true",
                    help="skip the Nelder-Mead reference optimum")
    ap.add_argument("--polish-maxfev", type=int, default=8000,
                    help="filter evaluations at most in the Nelder-Mead polish")
    ap.add_argument("--quick", action="store_true", help="400 samples, one warm repeat")
    ap.add_argument("--out", help="write the results as JSON here")
    ap.add_argument("--default-blas-threads", action="store_true",
                    help="do not set OPENBLAS_NUM_THREADS=1 (see benchmarks/fit.py)")
    args = ap.parse_args()
    if args.quick:
        args.samples, args.repeats = 400, 1
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', '(unset)')}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")

    t0 = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    from thermojax.fitting._fit import fit
    from thermojax.measurements._data import Experiment
    from thermojax.model._model_file import parse_model
    t_import = time.perf_counter() - t0
    assert jax.config.jax_compilation_cache_dir is None, "the persistent cache must be off"

    t, U = inputs(args.samples)
    p_start = start_params(U)
    spec_text = MODEL.format(*(repr(float(v)) for v in p_start))
    print(f"four-node building: {args.samples} samples at {DT:g} s "
          f"({args.samples * DT / 86400:.1f} days), one sensor (air), {len(NAMES)} free "
          f"parameters; thermojax + JAX import {t_import:.2f} s (not timed below)")

    def run_thermojax(seed):
        Y = measurements(U, seed)
        spec = parse_model(spec_text, "building4.toml")
        tic = time.perf_counter()
        res = fit(spec, [Experiment(t, U, Y[:, None], "building4")], likelihood="kalman")
        wall = time.perf_counter() - tic
        p = np.array([res.parameters[nm]["value"] for nm in NAMES])
        return dict(seed=seed, wall=wall, nll=float(res.nll), p=p, converged=bool(res.converged),
                    n_steps=int(res.n_steps), message=str(res.message),
                    numpy_nll=float(kalman_nll(p, U, Y)), Y=Y,
                    at_bound=[nm for nm in NAMES if res.parameters[nm].get("at_bound")])

    first = run_thermojax(0)
    print(f"  thermojax first fit (compiles): {first['wall']:.2f} s, -log L {first['nll']:.4f}, "
          f"{first['n_steps']} steps, converged {first['converged']}")
    warm = []
    for seed in range(1, args.repeats + 1):
        r = run_thermojax(seed)
        warm.append(r)
        print(f"  thermojax warm fit (seed {seed}): {r['wall']:.3f} s, -log L {r['nll']:.4f}")
    sp = scipy_fit(U, first["Y"], p_start, polish=not args.no_polish,
                   polish_maxfev=args.polish_maxfev)
    print(f"  scipy L-BFGS-B: {sp['wall']:.2f} s, -log L {sp['nll']:.4f}, {sp['nfev']} "
          f"evaluations, {sp['nit']} iterations ({sp['message']})")
    if "ref_nll" in sp:
        print(f"  Nelder-Mead polish (reference): {sp['ref_wall']:.2f} s, -log L "
              f"{sp['ref_nll']:.4f}, {sp['ref_nfev']} evaluations")

    # ---- report
    ref = sp.get("ref_nll", sp["nll"])
    ref_label = "Nelder-Mead polish" if "ref_nll" in sp else "L-BFGS-B (no polish)"
    t_warm = float(np.median([r["wall"] for r in warm])) if warm else float("nan")
    print()
    print(f"Seed 0, the same data for all ({args.samples} samples):")
    print(f"  {'':<42}{'-log L':>14}{'- reference':>14}{'wall s':>10}")
    print(f"  {'thermojax first fit (compilation incl.)':<42}{first['nll']:>14.4f}"
          f"{first['nll'] - ref:>+14.4f}{first['wall']:>10.2f}")
    print(f"  {'  same optimum by the NumPy filter':<42}{first['numpy_nll']:>14.4f}"
          f"{first['numpy_nll'] - ref:>+14.4f}")
    print(f"  {'scipy L-BFGS-B (2-point differences)':<42}{sp['nll']:>14.4f}"
          f"{sp['nll'] - ref:>+14.4f}{sp['wall']:>10.2f}")
    if "ref_nll" in sp:
        print(f"  {'reference: L-BFGS-B + Nelder-Mead':<42}{ref:>14.4f}{0.0:>+14.4f}"
              f"{sp['wall'] + sp['ref_wall']:>10.2f}")
    print(f"  thermojax vs its own likelihood in NumPy: {first['nll'] - first['numpy_nll']:+.2e}")
    print(f"  thermojax process noises at zero: {first['at_bound'] or 'none'}")
    print(f"  warm thermojax fits (new noise): median {t_warm:.3f} s over {len(warm)} "
          "(" + ", ".join(f"{r['wall']:.3f}" for r in warm) + ")")

    print()
    print("Parameters (seed 0):")
    p_true = truth_params(U)
    print(f"  {'parameter':<38}{'true':>11}{'start':>11}{'thermojax':>11}{'scipy':>11}"
          + (f"{'reference':>11}" if "ref_p" in sp else ""))
    for i, nm in enumerate(NAMES):
        row = [p_true[i], p_start[i], first["p"][i], sp["p"][i]]
        if "ref_p" in sp:
            row.append(sp["ref_p"][i])
        print(f"  {nm:<38}" + "".join(f"{v:>11.4g}" for v in row))

    print()
    r_first = sp["wall"] / first["wall"]
    r_warm = sp["wall"] / t_warm
    same = first["nll"] <= ref + 0.05
    print("Ratios (same run) and targets:")
    print(f"  scipy L-BFGS-B / thermojax first fit {r_first:>9.2f}   target >= 20: "
          f"{'met' if r_first >= 20 else 'NOT met'}")
    print(f"  scipy L-BFGS-B / thermojax warm fit  {r_warm:>9.2f}")
    print(f"  thermojax first fit {first['wall']:.2f} s           target <= 15 s: "
          f"{'met' if first['wall'] <= 15 else 'NOT met'}")
    print(f"  thermojax -log L within 0.05 of the reference ({ref_label}): "
          f"{'yes' if same else 'NO'} ({first['nll'] - ref:+.4f}); scipy L-BFGS-B "
          f"{sp['nll'] - ref:+.4f}")
    if args.samples != 1700:
        print(f"  (the targets are for 1,700 samples; this run has {args.samples})")

    if args.out:
        def clean(d):
            return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()
                    if k != "Y"}
        out = dict(samples=args.samples, dt=DT, names=NAMES, truth=p_true.tolist(),
                   start=p_start.tolist(), import_s=t_import,
                   blas_threads=os.environ.get("OPENBLAS_NUM_THREADS"),
                   load_average=os.getloadavg()[0], thermojax_first=clean(first),
                   thermojax_warm=[clean(r) for r in warm], scipy=clean(sp),
                   reference_nll=ref, reference=ref_label,
                   ratio_first=r_first, ratio_warm=r_warm,
                   targets=dict(ratio_ge_20=r_first >= 20, first_le_15s=first["wall"] <= 15,
                                same_optimum=bool(same)))
        with open(args.out, "w") as fh:
            json.dump(out, fh, indent=1)
        print(f"results written to {args.out}")


if __name__ == "__main__":
    main()
