"""Experiment design for the six-node IMU: a four-hour chamber profile, D-optimal.

thermojax: `thermojax.design.design(imu6, 4 h, dt = 1 s)` from four starts: the criterion's
exact gradient through the sampled inputs and the fit's forward sensitivities (JAX), and
L-BFGS-B (SciPy) on it. Timed cold (compilation included) and the search alone.

Peer: the same search (the same schedule, criterion, prior and marginalized starts) with
SciPy alone: the readings simulated by an exact-hold NumPy recurrence (`scipy.linalg.expm`
of the augmented system), their sensitivities by central differences in the parameters'
logs and the starts, and the criterion's gradient by forward differences over the schedule
numbers, L-BFGS-B again. One such gradient costs `n + 1` criterion evaluations; the peer
runs within `--scipy-budget` seconds and its time for the iterations thermojax used is
extrapolated from its measured time per evaluation.

Usage:  python benchmarks/design.py [--hours 4] [--starts 4] [--scipy-budget 120]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
import scipy.optimize  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def numpy_schedule(z, sch):
    """`ProfileSchedule.sampled` in NumPy."""
    lim, K = sch.limits, sch.temperature_segments
    lo_c, hi_c = lim.temperature_c
    step = lim.ramp_c_per_min / 60.0 * (sch.duration_s / max(K, 1))
    knots = [lim.start_c]
    for k in range(K):
        T = knots[-1]
        lo, hi = max(-step, lo_c - T), min(step, hi_c - T)
        knots.append(T + lo + (hi - lo) / (1 + np.exp(-z[k])))
    T = np.interp(sch.ts, sch.knot_times, knots)
    plo, phi = lim.power_w
    levels = plo + (phi - plo) / (1 + np.exp(-z[K:]))
    seg = np.clip(np.floor(sch.ts / (sch.duration_s / sch.power_segments) + 1e-9), 0,
                  sch.power_segments - 1).astype(int)
    P = levels[seg]
    P[0] = lim.start_power_w
    return T, P


class ScipyPeer:
    """The criterion with SciPy: exact-hold NumPy simulation, finite-difference sensitivities."""

    def __init__(self, spec, names, sigma, sch):
        from thermojax.fitting._identifiability import _thermal_matrices

        self.spec, self.sch, self.sigma = spec, sch, np.asarray(sigma)
        self.judged = [n for n in names if not n.endswith(".initial")]
        nodes = spec.node_names
        self.starts = [nodes.index(n.split(".")[3]) for n in names if n.endswith(".initial")]
        self.values = {}
        for n in self.judged:
            kind, key, what = n.split(".")
            table = {"nodes": spec.nodes, "links": spec.links, "boundaries": spec.boundaries,
                     "heat_inputs": spec.heat_inputs}[kind]
            item = next(x for x in table if getattr(x, "name", getattr(x, "key", None)) == key)
            self.values[n] = getattr(item, what).value
        self.matrices = _thermal_matrices
        self.dt = sch.dt

    def _discrete(self, values):
        A, B, C = self.matrices(self.spec, values)
        n, m = B.shape
        M = np.zeros((n + 2 * m, n + 2 * m))
        M[:n, :n], M[:n, n:n + m] = A, B
        M[n:n + m, n + m:] = np.eye(m)
        E = scipy.linalg.expm(M * self.dt)[:n]
        # chamber linear between samples (first input), power held (second)
        return A, B, C, E[:, :n], E[:, n:n + m], E[:, n + m:]

    def readings(self, values, U, dx0=None):
        A, B, C, Phi, G, S = self._discrete(values)
        x = np.linalg.solve(A, -B @ U[0])
        if dx0 is not None:
            x = x + dx0
        slopes = np.diff(U, axis=0) / self.dt
        slopes[:, 1] = 0.0  # the power is held
        drive = U[:-1] @ G.T + slopes @ S.T
        X = np.empty((U.shape[0], x.size))
        X[0] = x
        for k in range(1, U.shape[0]):
            x = Phi @ x + drive[k - 1]
            X[k] = x
        return X @ C.T

    def loss(self, z):
        T, P = numpy_schedule(z, self.sch)
        U = np.stack([T, P], axis=1)
        cols = []
        for n in self.judged:
            hi = dict(self.values, **{n: self.values[n] * np.exp(1e-6)})
            lo = dict(self.values, **{n: self.values[n] * np.exp(-1e-6)})
            cols.append((self.readings(hi, U) - self.readings(lo, U)) / 2e-6)
        # a start estimated per node; the other nodes start at rest given those (as the
        # fit lays starts out): they move by -A_uu^-1 A_us
        A = self.matrices(self.spec, self.values)[0]
        s = np.array(self.starts)
        u = np.setdiff1d(np.arange(A.shape[0]), s)
        base = self.readings(self.values, U)
        for i in self.starts:
            e = np.zeros(A.shape[0])
            e[i] = 1.0
            if u.size:
                e[u] = -np.linalg.solve(A[np.ix_(u, u)], A[np.ix_(u, s)] @ e[s])
            cols.append(self.readings(self.values, U, e) - base)  # linear in the start
        J = (np.stack(cols, -1) / self.sigma[None, :, None]).reshape(-1, len(cols))
        F = J.T @ J
        k = len(self.judged)
        Fm = F[:k, :k] - F[:k, k:] @ np.linalg.solve(F[k:, k:], F[k:, :k])
        L = np.linalg.cholesky(0.5 * (Fm + Fm.T) + np.eye(k))
        return -2.0 * np.sum(np.log(np.diag(L)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=4.0)
    ap.add_argument("--starts", type=int, default=4)
    ap.add_argument("--scipy-budget", type=float, default=120.0)
    args = ap.parse_args()
    import thermojax  # noqa: F401
    from thermojax.design import design
    from thermojax.model import load_model

    print(f"load average {os.getloadavg()[0]:.2f}; OPENBLAS_NUM_THREADS="
          f"{os.environ['OPENBLAS_NUM_THREADS']}")
    spec = load_model(ROOT / "thermojax" / "data" / "imu6.toml")
    duration = args.hours * 3600.0
    t0, c0 = time.perf_counter(), time.process_time()
    d = design(spec, duration, dt=1.0, n_starts=args.starts)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"thermojax: imu6, {args.hours:g} h at 1 s ({d.schedule.n_times} samples), "
          f"{d.schedule.n_parameters} schedule numbers, {args.starts} starts: {wall:.1f} s "
          f"cold ({cpu:.1f} s CPU), search {d.wall_time_s:.1f} s, {d.n_iterations} "
          f"iterations, {d.n_evaluations} criterion+gradient evaluations")
    print(f"  ({d.wall_time_s / max(d.n_evaluations, 1) * 1e3:.1f} ms per criterion+gradient, "
          "compilation included)")
    for name, ref in d.references.items():
        ratios = [d.designed.stds[p] / ref.stds[p] for p in d.designed.stds
                  if d.designed.stds[p] is not None and ref.stds[p] is not None]
        print(f"  designed / {name}: geometric mean of the std ratios "
              f"{np.exp(np.mean(np.log(ratios))):.3g} over {len(ratios)} parameters; "
              f"per parameter " + ", ".join(f"{r:.2g}" for r in ratios))

    peer = ScipyPeer(spec, d.problem.names, d.problem.sigma, d.schedule)
    z = np.zeros(d.schedule.n_parameters)
    t0 = time.perf_counter()
    v = peer.loss(z)
    t_eval = time.perf_counter() - t0
    print(f"SciPy peer: one criterion {t_eval:.2f} s ({2 * len(peer.judged) + 2 * len(peer.starts)}"
          f" simulations of {d.schedule.n_times} samples); value {v:.6g} vs thermojax "
          f"{d.references and float(_jax_loss(d, z)):.6g}")
    n_grad = d.schedule.n_parameters + 1
    print(f"  one forward-difference gradient: {n_grad} criteria, about {n_grad * t_eval:.0f} s")
    evals, t0 = 0, time.perf_counter()

    def fun(x):
        nonlocal evals
        evals += 1
        if time.perf_counter() - t0 > args.scipy_budget:
            raise TimeoutError
        return peer.loss(x)

    try:
        scipy.optimize.minimize(fun, z, method="L-BFGS-B",
                                bounds=[(-8, 8)] * d.schedule.n_parameters,
                                options={"maxiter": 5})
    except TimeoutError:
        pass
    spent = time.perf_counter() - t0
    per = spent / max(evals, 1)
    need = d.n_evaluations * n_grad * per
    print(f"  within the {args.scipy_budget:g} s budget: {evals} criteria ({per:.2f} s each); "
          f"the {d.n_evaluations} gradient evaluations thermojax's search used would take "
          f"about {need / 3600:.1f} h ({need / d.wall_time_s:.0f}x thermojax's search)")


def _jax_loss(d, z):
    import jax.numpy as jnp

    from thermojax.design import criterion_loss, marginal_information

    T, P = d.schedule.sampled(jnp.asarray(z))
    F = d.problem.information(d.problem.inputs(T, P))
    return criterion_loss(marginal_information(F, d.problem.nuisance), "d")


if __name__ == "__main__":
    main()
