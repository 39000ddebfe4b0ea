"""The cost of discovery beyond the vocabulary (docs/formats.md §3a), per loop step.

1. The missing heat: thermojax's reconstruction (`thermojax.missing_heat`: the
   likelihood's choice of carrying nodes and intensity, then the RTS smoother) against
   the same smoother written the way a user would without it, in NumPy with
   `scipy.linalg.expm` (a Python loop over samples, one intensity at a time), on the
   same fitted model and runs. Both must agree on the reconstructed heat.
2. A step of `investigate` on a case whose truth is a law outside the vocabulary: its
   wall time, the missing heat's share, and the law it learns.

The data are the hidden-effect generator's (`tests/hidden/`, its own Radau
integration). Usage:  python benchmarks/discovery.py [--case NAME] [--horizon S]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.linalg

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from hidden import generator as g  # noqa: E402

import thermojax as tj  # noqa: E402


def numpy_smoother(A, cap, H, R, carriers, s, dt, e, mask, var0, d_std):
    """The error model of `thermojax.missing_heat`, by hand: Van Loan discretization,
    a Kalman filter and an RTS smoother as Python loops. Returns (log L, heat, std)."""
    n, k = A.shape[0], len(carriers)
    G = np.zeros((n, k))
    G[carriers, np.arange(k)] = 1 / cap[carriers]
    Ac = np.block([[A, G], [np.zeros((k, n + k))]])
    Lc = np.diag(np.r_[np.zeros(n), (s * cap[carriers]) ** 2])
    N = n + k
    E = scipy.linalg.expm(np.block([[-Ac, Lc], [np.zeros((N, N)), Ac.T]]) * dt)
    F = E[N:, N:].T
    Q = F @ E[:N, N:]
    Hz = np.hstack([H, np.zeros((H.shape[0], k))])
    z, P = np.zeros(N), np.diag(np.r_[var0 * 1e-4, d_std ** 2])
    ll, zf, Pf, zp, Pp = 0.0, [], [], [], []
    for ek, mk in zip(e, mask):
        Rk = np.where(mk, R, 1e12)
        S = Hz @ P @ Hz.T + np.diag(Rk)
        v = np.where(mk, ek - Hz @ z, 0.0)
        K = np.linalg.solve(S, Hz @ P).T
        z = z + K @ v
        IKH = np.eye(N) - K @ Hz
        P = IKH @ P @ IKH.T + K @ np.diag(Rk) @ K.T
        sign, logdet = np.linalg.slogdet(S)
        ll -= 0.5 * (logdet - (~mk).sum() * np.log(1e12) + v @ np.linalg.solve(S, v)
                     + mk.sum() * np.log(2 * np.pi))
        zf.append(z), Pf.append(P)
        z, P = F @ z, F @ P @ F.T + Q
        zp.append(z), Pp.append(P)
    zs, Ps = zf[-1], Pf[-1]
    heat, std = [zs[n:]], [np.sqrt(np.diag(Ps)[n:])]
    for t in range(len(e) - 2, -1, -1):
        Gk = np.linalg.solve(Pp[t], F @ Pf[t]).T
        zs = zf[t] + Gk @ (zs - zp[t])
        Ps = Pf[t] + Gk @ (Ps - Pp[t]) @ Gk.T
        heat.append(zs[n:]), std.append(np.sqrt(np.diag(Ps)[n:]))
    return ll, np.array(heat[::-1]), np.array(std[::-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="law_quadratic_input")
    ap.add_argument("--horizon", type=float, default=3600.0)
    args = ap.parse_args()
    from thermojax.discovery._missing_heat import _ErrorModel  # the same inputs for both

    case = g.load_case(args.case)
    believed = tj.parse_model(g.dump_toml(case["believed"]))
    raw = g.generate_case(args.case, seed=0, horizon_s=args.horizon)
    exps = [tj.Experiment(ts, np.stack([c[k] for k in believed.input_columns], 1),
                          np.stack([c[k] for k in believed.sensor_columns], 1))
            for ts, c in raw]
    res = tj.fit(believed, exps)
    print(f"case {args.case}: {len(raw)} runs x {args.horizon:g} s at 1 Hz, "
          f"{len(believed.node_names)} nodes")

    t0 = time.perf_counter()
    mh = tj.missing_heat(res)
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    mh = tj.missing_heat(res)
    warm = time.perf_counter() - t0
    print(f"thermojax missing_heat: {cold:.1f} s cold (compilation), {warm:.2f} s warm; "
          f"carriers {mh.carriers}, s = {mh.intensity:.3g}")

    em = _ErrorModel(res)
    carriers = [list(res.lowered_spec.node_names).index(n) for n in mh.carriers]
    A, cap, H = (np.asarray(x) for x in (em.A, em.capacitance, em.H))
    t0 = time.perf_counter()
    worst = 0.0
    for r, (run, n_t) in enumerate(zip(em.runs, em.lengths)):
        _, heat, std = numpy_smoother(A, cap, H, np.asarray(em.R), carriers, mh.intensity,
                                      run.dt, run.e[:n_t], run.mask[:n_t], em.initial_var,
                                      cap[carriers] / 60.0)
        cols = [mh.nodes.index(n) for n in mh.carriers]
        worst = max(worst, float(np.max(np.abs(heat - mh.heat[r][:, cols]))))
    one = time.perf_counter() - t0
    # thermojax evaluates 2 x 15 intensities per carrier set tried; NumPy would too
    tried = sum(len(res.lowered_spec.node_names) - i for i in range(len(mh.carriers) + 1))
    print(f"NumPy/SciPy smoother, one intensity: {one:.2f} s; the same search "
          f"({tried} carrier sets x 30 intensities) ~ {one * tried * 30:.0f} s")
    print(f"ratio (NumPy search / thermojax warm): {one * tried * 30 / warm:.0f}x; "
          f"largest difference in the reconstructed heat {worst:.2e} W")

    with tempfile.TemporaryDirectory() as tmp:
        files = g.write_case(args.case, Path(tmp) / "data", seed=0, horizon_s=args.horizon)
        runs = [tj.read_telemetry(p) for p in files["data"]]
        t0 = time.perf_counter()
        plain = tj.investigate(believed, runs, max_steps=1)
        total = time.perf_counter() - t0
    added = plain["steps"][-1]["added"]
    print(f"investigate, one step (compilation included): {total:.0f} s, of which the "
          f"missing heat ~{cold:.0f} s cold; added "
          f"{added and (added['kind'], added.get('expression'))}; RMSE "
          f"{ {c: round(v, 4) for c, v in plain['steps'][-1]['rmse'].items()} }")


if __name__ == "__main__":
    main()
