"""Large networks: time and peak memory of a fit against the number of nodes, with the
fitted growth exponents, beside SciPy `least_squares`.

A chain of `n` nodes (`_chain_data`: capacitances and conductances drawn around 10 J/K
and 1 W/K, both ends to the chamber air, a heater on every fifth node, a sensor on every
node, 400 samples at 2 s, the nodes starting from a random profile). Free: every
capacitance, link and boundary conductance and each node's start: `P = 3n + 1`
parameters. Every fitter starts from the same point, the truth times `e^N(0, 0.2²)`.

Fitters, each in a fresh process (its peak resident memory is the process's, its time
the fit's wall time, compilation included):

- thermojax `fit(..., jacobian="auto")`: the adjoint path from 50 nodes on (the forward
  sensitivities' predicted time passes a minute), forward sensitivities below;
- thermojax `fit(..., jacobian="forward")` where it finishes in reasonable time
  (`--forward-max`, default 40 nodes);
- SciPy `least_squares` (TRF, 2-point finite differences, `x_scale="jac"`) on NumPy
  residuals: `scipy.linalg.expm` of the augmented matrix, then the recurrence. A sparse
  Jacobian does not apply: every parameter moves every sensor within the 400 samples,
  so the Jacobian has no zero block to declare (`--scipy-max`, default 50 nodes).

Each row says how far the fit's values are from the generated truth in its own stds
(`max |z|` over the capacitances and conductances; thermojax only, SciPy has no noise
model). The exponents are least-squares slopes of log time and log memory against log n
over the adjoint path's sizes. Ratios are SciPy's time over thermojax's, same size, same
run of this script.

    python benchmarks/large_networks.py [--sizes 10 20 50 100 200] [--scipy-max 50]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def _problem(n: int):
    from _chain_data import chain_run, chain_text, chain_truth

    C, G, Gb = chain_truth(n)
    ts, U, Y, x0 = chain_run(n, n_times=400, dt=2.0)
    rng = np.random.default_rng(100 + n)
    start = (C * np.exp(0.2 * rng.standard_normal(n)),
             G * np.exp(0.2 * rng.standard_normal(n - 1)), Gb * np.exp(0.2 * rng.standard_normal(2)))
    return (C, G, Gb), start, (ts, U, Y, x0), chain_text


def _one_thermojax(n: int, jacobian: str) -> dict:
    import warnings

    import thermojax as tj
    from thermojax.measurements._data import Experiment

    truth, start, (ts, U, Y, _), chain_text = _problem(n)
    spec = tj.parse_model(chain_text(n, *start))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the run is shorter than the chain's slowest mode
        res = tj.fit(spec, [Experiment(ts, U, Y, "chain")], jacobian=jacobian,
                     restart_plateaus=False)
    wall = time.perf_counter() - t0
    names = ([f"nodes.n{i}.capacitance" for i in range(n)]
             + [f"links.n{i}-n{i + 1}.conductance" for i in range(n - 1)])
    values = np.concatenate(truth[:2])
    z = np.array([(res.parameters[k]["value"] - v) / res.parameters[k]["std"]
                  if res.parameters[k]["std"] else np.nan for k, v in zip(names, values)])
    return {"time_s": wall, "converged": bool(res.converged), "nll": float(res.nll),
            "n_free": len(res.free_names), "max_abs_z": float(np.nanmax(np.abs(z))),
            "beyond_3": int(np.sum(np.abs(z) >= 3)), "n_z": int(np.sum(np.isfinite(z))),
            "method": res.method.split(":")[0]}


def _one_scipy(n: int) -> dict:
    import scipy.linalg
    import scipy.optimize
    from _chain_data import chain_matrices

    truth, start, (ts, U, Y, _), _ = _problem(n)
    dt = ts[1] - ts[0]

    def residuals(p):
        C, G, Gb = np.exp(p[:n]), np.exp(p[n:2 * n - 1]), np.exp(p[2 * n - 1:2 * n + 1])
        A, B = chain_matrices(C, G, Gb)
        M = np.zeros((n + 2, n + 2))
        M[:n, :n], M[:n, n:] = A * dt, B * dt
        E = scipy.linalg.expm(M)
        Phi, Gam = E[:n, :n], E[:n, n:]
        x = np.empty((len(ts), n))
        x[0] = p[2 * n + 1:]
        for k in range(len(ts) - 1):
            x[k + 1] = Phi @ x[k] + Gam @ U[k]
        return ((Y - x) / 0.01).ravel()

    p0 = np.concatenate([np.log(start[0]), np.log(start[1]), np.log(start[2]), Y[0]])
    t0 = time.perf_counter()
    sol = scipy.optimize.least_squares(residuals, p0, method="trf", jac="2-point",
                                       x_scale="jac")
    wall = time.perf_counter() - t0
    err = np.abs(sol.x[:2 * n - 1] - np.log(np.concatenate(truth[:2])))
    return {"time_s": wall, "converged": bool(sol.status > 0), "nfev": int(sol.nfev),
            "cost": float(sol.cost), "max_log_error": float(err.max())}


def _child(kind: str, n: int) -> dict:
    """One fit in a fresh process: its result and peak resident memory (GB)."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    for k in ("THERMOJAX_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR"):
        env.pop(k, None)
    out = subprocess.run([sys.executable, __file__, "--one", kind, str(n)], env=env,
                         capture_output=True, text=True, check=False)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _slope(ns, ys) -> float:
    return float(np.polyfit(np.log(ns), np.log(ys), 1)[0]) if len(ns) > 1 else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 50, 100, 200])
    ap.add_argument("--scipy-max", type=int, default=50)
    ap.add_argument("--forward-max", type=int, default=40)
    ap.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        kind, n = args.one[0], int(args.one[1])
        result = _one_scipy(n) if kind == "scipy" else _one_thermojax(n, kind)
        result["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        print(json.dumps(result))
        return
    rows = []
    print("| n | P | path | time | peak memory | max abs z (C, G) | forward sensitivities | "
          "SciPy least_squares | SciPy / thermojax |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in args.sizes:
        auto = _child("auto", n)
        fwd = _child("forward", n) if n <= args.forward_max else None
        sp = _child("scipy", n) if n <= args.scipy_max else None
        rows.append((n, auto))

        def fmt(r):
            if r is None:
                return "–"
            if "error" in r:
                return f"failed ({r['error'][:60]})"
            return f"{r['time_s']:.1f} s, {r['peak_gb']:.2f} GB"

        ratio = (f"{sp['time_s'] / auto['time_s']:.2g}×" if sp and "error" not in sp
                 and "error" not in auto else "–")
        if "error" in auto:
            print(f"| {n} | – | – | {fmt(auto)} | | | {fmt(fwd)} | {fmt(sp)} | – |", flush=True)
            continue
        print(f"| {n} | {auto['n_free']} | {auto['method']} | {auto['time_s']:.1f} s | "
              f"{auto['peak_gb']:.2f} GB | {auto['max_abs_z']:.2f} "
              f"({auto['beyond_3']} of {auto['n_z']} beyond 3) | {fmt(fwd)} | {fmt(sp)} | {ratio} |",
              flush=True)
    adj = [(n, r) for n, r in rows if "error" not in r and r["method"] == "adjoint"]
    if len(adj) > 1:
        ns = [n for n, _ in adj]
        print(f"\nadjoint path, n = {ns[0]}..{ns[-1]}: time ~ n^{_slope(ns, [r['time_s'] for _, r in adj]):.2f}, "
              f"peak memory ~ n^{_slope(ns, [r['peak_gb'] for _, r in adj]):.2f}")


if __name__ == "__main__":
    main()
