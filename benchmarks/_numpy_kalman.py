"""The SciPy peer's continuous-discrete Kalman filter, in plain NumPy: what a user would
write instead of thermojax (`kalman_imu6.py`, `kalman_prbs1.py`). Nothing here imports
thermojax.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg
import scipy.optimize


def discretize(A, B, dt, foh):
    """`x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]` exactly, from `expm` of the augmented
    block matrix; `foh` (inputs,) bool: piecewise linear inputs, else held constant."""
    n, m = B.shape
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n], M[:n, n:n + m], M[n:n + m, n + m:] = A * dt, B * dt, np.eye(m)
    E = scipy.linalg.expm(M)
    B1 = E[:n, n + m:] * np.asarray(foh, float)
    return E[:n, :n], E[:n, n:n + m] - B1, B1


def van_loan(A, q, dt):
    """`Qd = ∫0^dt e^{As} diag(q²) e^{Aᵀs} ds`: Van Loan's block exponential on `h = dt /
    2^j` with `‖A‖₁ h <= 1` (stiff nodes overflow it otherwise), doubled back by
    `Qd(2h) = Qd(h) + Phi(h) Qd(h) Phi(h)ᵀ`."""
    n = A.shape[0]
    j = max(0, int(np.ceil(np.log2(max(np.abs(A).sum(axis=0).max() * dt, 1.0)))))
    h = dt / 2**j
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A * h, np.diag(q * q) * h, A.T * h
    F = scipy.linalg.expm(M)
    Phi = F[n:, n:].T
    Qd = Phi @ F[:n, n:]
    for _ in range(j):
        Qd = Qd + Phi @ Qd @ Phi.T
        Phi = Phi @ Phi
    return 0.5 * (Qd + Qd.T)


def kalman_nll(A, B, sensors, q, r, U, Y, dt, foh, x0, P0):
    """−log L of the filter (update before predict, every sample measured): `A` (n, n)
    1/s, `B` (n, m), `sensors` the measured node of each output, `q` (n,) process-noise
    stds K/√s, `r` (p,) sensor-noise stds K, `U` (T, m), `Y` (T, p), `x0` (n,), `P0`
    (n, n)."""
    Phi, B0, B1 = discretize(A, B, dt, foh)
    Qd = van_loan(A, q, dt)
    R = np.diag(np.asarray(r, float) ** 2)
    n = A.shape[0]
    H = np.zeros((len(sensors), n))
    H[np.arange(len(sensors)), sensors] = 1.0
    drive = U @ B0.T + np.concatenate([U[1:], U[-1:]]) @ B1.T
    m, P, eye = np.array(x0, float), np.array(P0, float), np.eye(n)
    total = 0.5 * Y.size * np.log(2 * np.pi)
    for k in range(len(Y)):  # plain NumPy on small arrays: each call costs microseconds
        PH = P[:, sensors]
        S = PH[sensors] + R
        Sinv = np.linalg.inv(S)
        e = Y[k] - m[sensors]
        total += 0.5 * (np.log(np.linalg.det(S)) + e @ Sinv @ e)
        K = PH @ Sinv
        IKH = eye - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        m = Phi @ (m + K @ e) + drive[k]
        P = Phi @ P @ Phi.T + Qd
    return float(total)


def read_log(csv, inputs, outputs):
    """`(U (T, inputs), Y (T, outputs))` from a telemetry CSV (`#` lines skipped)."""
    lines = [ln for ln in open(csv).read().splitlines() if not ln.startswith("#")]
    header = lines[0].split(",")
    data = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    cols = lambda names: data[:, [header.index(c) for c in names]]  # noqa: E731
    return cols(inputs), cols(outputs)


class Network:
    """A model TOML (docs/formats.md §2, read with `tomllib`) as the peer builds it by
    hand: `x` (free,) the optimizer's vector, `bounds` for L-BFGS-B, `nll(x, U, Y, dt)`.
    Covers nodes, links, boundaries, heat inputs and sensors, nothing else; the initial
    mean is the equilibrium at the first input with the nodes that give `initial` set to
    it (estimated), P0 = diag(initial_std²)."""

    def __init__(self, toml: dict):
        self.nodes = [n["name"] for n in toml["nodes"]]
        idx = self.nodes.index
        self.inputs = list(dict.fromkeys([b["input"] for b in toml.get("boundaries", [])]
                                         + [h["input"] for h in toml.get("heat_inputs", [])]))
        self.foh = [next(e.get("hold", "foh") for e in (*toml.get("boundaries", []),
                                                        *toml.get("heat_inputs", []))
                         if e["input"] == c) == "foh" for c in self.inputs]
        self.links = [tuple(idx(b) for b in k["between"]) for k in toml.get("links", [])]
        self.boundaries = [(idx(b["node"]), self.inputs.index(b["input"]))
                           for b in toml.get("boundaries", [])]
        self.heat = [(idx(h["node"]), self.inputs.index(h["input"]))
                     for h in toml.get("heat_inputs", [])]
        self.sensors = [idx(s["node"]) for s in toml["sensors"]]
        self.columns = [s["column"] for s in toml["sensors"]]
        self.initial = [i for i, n in enumerate(toml["nodes"]) if "initial" in n]
        self.initial_std = np.array([n.get("initial_std", 1.0) for n in toml["nodes"]])
        entries = ([n["capacitance"] for n in toml["nodes"]]
                   + [k["conductance"] for k in toml.get("links", [])]
                   + [b["conductance"] for b in toml.get("boundaries", [])]
                   + [h.get("gain", 1.0) for h in toml.get("heat_inputs", [])]
                   + [s.get("noise", 0.01) for s in toml["sensors"]]
                   + [n.get("process_noise", 0.0) for n in toml["nodes"]]
                   + [toml["nodes"][i]["initial"] for i in self.initial])
        self.values = np.array([e["value"] if isinstance(e, dict) else e for e in entries],
                               float)
        self.free = np.array([not (isinstance(e, dict) and e.get("fixed", False))
                              for e in entries])
        n, nl, nb, nh, ns = (len(self.nodes), len(self.links), len(self.boundaries),
                             len(self.heat), len(self.sensors))
        ends = np.cumsum([n, nl, nb, nh, ns, n, len(self.initial)])
        self.parts = dict(zip(("c", "g", "gb", "gain", "r", "q", "x0"),
                              (slice(a, b) for a, b in zip([0, *ends[:-1]], ends))))
        # logs of the positive parameters; process-noise stds linear with q >= 0 (so zero
        # is reachable, as an expert bounds them), initial temperatures in °C
        self.log = np.arange(len(entries)) < ends[4]
        q = self.parts["q"]
        self.bounds = [(0.0, None) if q.start <= i < q.stop else (None, None)
                       for i in np.flatnonzero(self.free)]

    def x(self, values=None) -> np.ndarray:
        """The optimizer's vector (free,) at physical `values` (default the file's)."""
        v = self.values if values is None else values
        return np.where(self.log, np.log(np.where(self.log, v, 1.0)), v)[self.free]

    def full(self, x) -> np.ndarray:
        """Every physical value at the optimizer's `x`."""
        v, lg = self.values.copy(), self.log[self.free]
        v[self.free] = np.where(lg, np.exp(np.where(lg, x, 0.0)), x)
        return v

    def fitted(self, toml: dict, report: dict) -> np.ndarray:
        """Physical values of thermojax's fit of one run: its `model.toml` (read as
        `toml`) with the run's estimated initial temperatures from its `report.json`
        (the TOML keeps the file's)."""
        v = Network(toml).values
        v[self.parts["x0"]] = [report["parameters"][f"runs.0.nodes.{self.nodes[i]}.initial"]
                               ["value"] for i in self.initial]
        return v

    def matrices(self, v):
        """`A` (n, n) 1/s and `B` (n, inputs) at physical values `v`."""
        p = self.parts
        c, n = v[p["c"]], len(self.nodes)
        K, B = np.zeros((n, n)), np.zeros((n, len(self.inputs)))
        for (i, j), g in zip(self.links, v[p["g"]]):
            K[[i, j], [i, j]] += g
            K[i, j] -= g
            K[j, i] -= g
        for (i, u), g in zip(self.boundaries, v[p["gb"]]):
            K[i, i] += g
            B[i, u] += g
        for (i, u), g in zip(self.heat, v[p["gain"]]):
            B[i, u] += g
        return -K / c[:, None], B / c[:, None]

    def nll(self, x, U, Y, dt) -> float:
        v = self.full(x)
        A, B = self.matrices(v)
        x0 = np.linalg.solve(A, -B @ U[0])
        x0[self.initial] = v[self.parts["x0"]]
        q = np.maximum(v[self.parts["q"]], 1e-12)  # a model file's zero, as thermojax reads it
        return kalman_nll(A, B, self.sensors, q, v[self.parts["r"]], U, Y,
                          dt, self.foh, x0, np.diag(self.initial_std ** 2))


class _Budget(Exception):
    pass


def fit_lbfgsb(net: Network, U, Y, dt, budget: float, target: float, maxiter=1000,
               ftol=None) -> dict:
    """`scipy.optimize.minimize(method="L-BFGS-B")` of `net.nll` from the file's values
    with SciPy's finite-difference gradient, stopped after `budget` s (`ftol`: SciPy's
    relative-reduction test, default SciPy's 2.2e-9). Also the time at which −log L first
    came within 1 of `target` (None if never), and `x`, the best point evaluated (a list)."""
    state = dict(calls=0, best=np.inf, reached=None, nit=0, x=net.x())
    t = time.perf_counter()

    def f(x):
        state["calls"] += 1
        v = net.nll(x, U, Y, dt)
        v = v if np.isfinite(v) else 1e300
        if v < state["best"]:
            state["best"], state["x"] = v, np.array(x)
        if state["reached"] is None and state["best"] <= target + 1.0:
            state["reached"] = time.perf_counter() - t
        return v

    def stop(_x):
        state["nit"] += 1
        if time.perf_counter() - t > budget:
            raise _Budget

    try:
        res = scipy.optimize.minimize(f, net.x(), method="L-BFGS-B", bounds=net.bounds,
                                      callback=stop, options=dict(
                                          maxiter=maxiter, **({} if ftol is None else
                                                              dict(ftol=ftol, gtol=0.0))))
        message, success = str(res.message), bool(res.success)
    except _Budget:
        message, success = f"stopped at the {budget:g} s budget", False
    return dict(wall=time.perf_counter() - t, nll=float(state["best"]), x=state["x"].tolist(),
                nit=state["nit"],
                nfev=state["calls"], success=success, message=message,
                reached_within_1=state["reached"])
