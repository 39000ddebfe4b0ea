"""The missing heat (docs/formats.md §3a): the heat flow per node that no term of a fitted
model accounts for, as a time series with its uncertainty.

Around the fitted model's free run `x_sim(t)` (nonlinear terms included), the error
`δx = x − x_sim` obeys the model's linear part (for a nonlinear model its terms'
Jacobians are left out of the error dynamics: an approximation where they are strong)
driven by a disturbance heat `d` (W) on some nodes, a
random walk of intensity `σ_i = s · C_i` (W/√s; `s` in K/s/√s, `C_i` the node's
capacitance):

    dδx/dt = A δx + diag(1/C) d + process noise,    dd/dt = σ w,    y − y_sim = H δx + v.

The augmented system is discretized exactly (Van Loan) per run, `s` is chosen by
maximum likelihood (a grid, then a finer one), the nodes carrying `d` greedily by the
likelihood (a node is added while BIC improves), and the Rauch–Tung–Striebel smoother
gives `d` with its std at every sample. A node given no disturbance has 0 ± 0: the data
are explained without heat there.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._discretize import discretize_process_noise
from ..dynamics._model_arrays import free_run_states, linear_parts

GRID = np.logspace(-8.0, -1.0, 15)  # s, K/s/√s: from no heat to a jump per sample
_MISSING_R = 1e12  # °C², the noise of an unmeasured sample (so it carries no weight)


@dataclass
class MissingHeat:
    """The reconstruction. Per run: `ts` (T,), `heat` and `heat_std` (T, nodes) in W,
    `temperatures` (T, nodes) the smoothed node temperatures (°C); `nodes` are the
    model's nodes (an added mass included, a lag's sensing element not), `carriers` the
    nodes the likelihood gave a disturbance, `intensity` its `s` (K/s/√s) and
    `log_likelihood_gain` the log-likelihood over the model without it."""

    nodes: tuple[str, ...]
    carriers: tuple[str, ...]
    intensity: float
    log_likelihood_gain: float
    ts: list[np.ndarray] = field(default_factory=list)
    heat: list[np.ndarray] = field(default_factory=list)
    heat_std: list[np.ndarray] = field(default_factory=list)
    temperatures: list[np.ndarray] = field(default_factory=list)

    def summary(self, file: str | None = None) -> dict:
        """The report's `missing_heat` entry: where, how much (RMS and peak, W)."""
        out = {"file": file, "nodes_carrying": list(self.carriers),
               "intensity_K_per_s_sqrt_s": self.intensity,
               "log_likelihood_gain": self.log_likelihood_gain, "per_node": {}}
        for j, n in enumerate(self.nodes):
            if n in self.carriers:
                q = np.concatenate([h[:, j] for h in self.heat])
                s = np.concatenate([h[:, j] for h in self.heat_std])
                out["per_node"][n] = {"rms_W": float(np.sqrt(np.mean(q ** 2))),
                                      "peak_W": float(q[np.argmax(np.abs(q))]),
                                      "median_std_W": float(np.median(s))}
        return out


def _filter(F, Q, H, R, z0, P0, e, mask):
    """Kalman filter of `z_{k+1} = F z_k + w`, `e_k = H z_k + v` (update before predict):
    log-likelihood, filtered means and covariances, and one-step predictions."""

    def step(carry, inp):
        z, P, ll = carry
        ek, mk = inp
        Rk = jnp.where(mk, R, _MISSING_R)
        S = H @ P @ H.T + jnp.diag(Rk)
        v = jnp.where(mk, ek - H @ z, 0.0)
        L = jnp.linalg.cholesky(S)
        Sinv_v = jax.scipy.linalg.cho_solve((L, True), v)
        K = jax.scipy.linalg.cho_solve((L, True), H @ P).T
        zf = z + K @ v
        IKH = jnp.eye(z.size) - K @ H
        Pf = IKH @ P @ IKH.T + K @ jnp.diag(Rk) @ K.T  # Joseph form
        logdet = 2 * jnp.sum(jnp.log(jnp.diag(L))) - jnp.sum(~mk) * math.log(_MISSING_R)
        ll = ll - 0.5 * (logdet + v @ Sinv_v + jnp.sum(mk) * math.log(2 * math.pi))
        zp, Pp = F @ zf, F @ Pf @ F.T + Q
        return (zp, 0.5 * (Pp + Pp.T), ll), (zf, Pf, zp, Pp)

    (_, _, ll), out = jax.lax.scan(step, (z0, P0, 0.0), (e, mask))
    return ll, out


def _smooth(F, zf, Pf, zp, Pp):
    """Rauch–Tung–Striebel: smoothed means and covariances from the filter's output."""
    def step(carry, inp):
        zs, Ps = carry
        zf_k, Pf_k, zp_k, Pp_k = inp
        G = jnp.linalg.solve(Pp_k, F @ Pf_k).T
        z = zf_k + G @ (zs - zp_k)
        P = Pf_k + G @ (Ps - Pp_k) @ G.T
        return (z, 0.5 * (P + P.T)), (z, P)

    last = (zf[-1], Pf[-1])
    _, (zs, Ps) = jax.lax.scan(step, last, (zf[:-1], Pf[:-1], zp[:-1], Pp[:-1]), reverse=True)
    return jnp.concatenate([zs, zf[-1:]]), jnp.concatenate([Ps, Pf[-1:]])


def _augmented(A, capacitance, carriers, q_x, sigma, dt):
    """`(F, Q)`: exact discretization of the error dynamics with disturbance heats on
    `carriers` (node indices) of intensity `sigma` (W/√s each)."""
    n, k = A.shape[0], len(carriers)
    G = jnp.zeros((n, k)).at[jnp.asarray(carriers), jnp.arange(k)].set(
        1.0 / capacitance[jnp.asarray(carriers)])
    Ac = jnp.block([[A, G], [jnp.zeros((k, n)), jnp.zeros((k, k))]])
    Lc = jnp.diag(jnp.concatenate([q_x ** 2, sigma ** 2]))
    # scaled and squared: one Van Loan block over a period many times a node's time
    # constant overflows and cancels into an indefinite Q (a NaN log L)
    return discretize_process_noise(Ac, Lc, dt)


class _Errors(NamedTuple):
    """The error model's arrays, and one run's residuals: the arguments of the compiled
    filters below, which take them whole (one program per state and carrier count, not
    one per operation)."""

    A: jax.Array  # (n, n) 1/s, the model's linear part
    capacitance: jax.Array  # (n,) J/K
    q_x: jax.Array  # (n,) the model's process noise, °C/√s
    H: jax.Array  # (p, n)
    R: jax.Array  # (p,) °C²
    initial_var: jax.Array  # (n,) °C²
    dt: jax.Array  # s
    e: jax.Array  # (T, p) °C, measured minus free run
    mask: jax.Array  # (T, p)


def _measurement(err: _Errors, carriers):
    """`(H, P0, z0)` of the state augmented with disturbances on `carriers`."""
    n, k = err.A.shape[0], carriers.shape[0]
    H = jnp.concatenate([err.H, jnp.zeros((err.H.shape[0], k))], 1)
    d_std = err.capacitance[carriers] / 60.0  # 1 K/min of heat a priori
    P0 = jnp.diag(jnp.concatenate([err.initial_var, d_std ** 2]))
    return H, P0, jnp.zeros(n + k)


@jax.jit
def _grid_loglik(err: _Errors, carriers, s_values):
    """log L of the run at each intensity of `s_values` (K/s/√s), disturbances on
    `carriers` (node indices)."""
    H, P0, z0 = _measurement(err, carriers)

    def one(s):
        F, Q = _augmented(err.A, err.capacitance, carriers, err.q_x,
                          s * err.capacitance[carriers], err.dt)
        return _filter(F, Q, H, err.R, z0, P0, err.e, err.mask)[0]
    return jax.vmap(one)(s_values)


@jax.jit
def _smoothed(err: _Errors, carriers, s):
    """Smoothed augmented means (T, n + k) and variances (T, n + k) of the run at
    intensity `s`."""
    H, P0, z0 = _measurement(err, carriers)
    F, Q = _augmented(err.A, err.capacitance, carriers, err.q_x, s * err.capacitance[carriers],
                      err.dt)
    _, (zf, Pf, zp, Pp) = _filter(F, Q, H, err.R, z0, P0, err.e, err.mask)
    zs, Ps = _smooth(F, zf, Pf, zp, Pp)
    return zs, jnp.diagonal(Ps, axis1=1, axis2=2)


@dataclass
class _Run:
    ts: np.ndarray
    dt: float
    e: np.ndarray  # (T, p) measured minus free-run prediction, °C
    mask: np.ndarray  # (T, p)
    x: np.ndarray  # (T, n) free-run states, °C


class _ErrorModel:
    """The fitted model's error dynamics and the runs' free-run residuals."""

    def __init__(self, result):
        model, data = result.model, result.problem.data
        p = len(result.lowered_spec.sensors)
        A, _, C, capacitance, offset = linear_parts(model)
        x = free_run_states(model, data, result.state.run_initial)
        x, H, offset = np.asarray(x), np.asarray(C)[:p], np.asarray(offset)[:p]
        self.A = jnp.asarray(A)
        self.capacitance = jnp.asarray(capacitance)
        self.H = jnp.asarray(H)
        self.R = jnp.asarray(np.asarray(model.noise)[:p] ** 2)
        self.q_x = (jnp.asarray(model.process_noise) if result.likelihood == "kalman"
                    else jnp.zeros(H.shape[1]))
        # a start the model states is known to 1 % of its std; a start estimated from the
        # data (a free parameter per run) is known no better than its prior: the fit set it
        # without the missing heat, so the reconstruction re-estimates it with the heat
        # (held tight, the start's bias came back as a heat at the run's start)
        estimated = np.array([n.initial is not None and not n.initial.fixed
                              for n in result.lowered_spec.nodes])
        self.initial_var = np.asarray(model.initial_std) ** 2 * np.where(estimated, 1.0, 1e-4)
        self.runs = []
        self.lengths = data.lengths
        for r, n_t in enumerate(data.lengths):
            # the padded grid (unmeasured after a run's end: no weight), so that every
            # run is the same compiled filter; `missing_heat` cuts the padding off
            y = np.asarray(data.outputs[r, :, :p])
            mask = np.asarray(data.mask[r, :, :p])
            pred = x[r] @ H.T + offset
            self.runs.append(_Run(np.asarray(data.ts[r]), float(data.dt[r]),
                                  np.where(mask, y - pred, 0.0), mask, x[r]))
        self.n_samples = int(sum(r.mask.sum() for r in self.runs))
        # each run's arrays on the device once, for every filter the search runs
        self._on_device = {id(run): _Errors(
            self.A, self.capacitance, self.q_x, self.H, self.R,
            *jax.device_put((self.initial_var, np.asarray(run.dt), run.e, run.mask)))
            for run in self.runs}

    def _errors(self, run: _Run) -> _Errors:
        return self._on_device[id(run)]

    def logliks(self, carriers, s_values) -> np.ndarray:
        """log L at each intensity of `s_values` (one vmapped filter per run)."""
        s_values = np.atleast_1d(np.asarray(s_values, float))
        carriers = np.asarray(list(carriers), int)
        return sum(np.asarray(_grid_loglik(self._errors(run), carriers, s_values))
                   for run in self.runs)

    def smooth(self, run, carriers, s):
        zs, var = _smoothed(self._errors(run), np.asarray(list(carriers), int), float(s))
        return np.asarray(zs), np.asarray(var)

    def baseline(self) -> float:
        """log L of the error model without disturbance (process noise only)."""
        return float(self.logliks([], [0.0])[0])


def _finite_or_worst(lls) -> np.ndarray:
    lls = np.asarray(lls, float)
    return np.where(np.isfinite(lls), lls, -np.inf)


def _best_intensity(em: _ErrorModel, carriers) -> tuple[float, float]:
    """`(s, log L)` maximizing the likelihood over `GRID`, then a finer grid around it.
    An intensity whose filter fails (a non-finite log L: seen on PRBS1 from 1e-5 up) is
    no candidate; where every one fails, log L is -inf and no carrier is added."""
    lls = _finite_or_worst(em.logliks(carriers, GRID))
    i = int(np.argmax(lls))
    fine = GRID[i] * np.logspace(-0.5, 0.5, GRID.size)  # one shape: one compiled filter
    lls_f = _finite_or_worst(em.logliks(carriers, fine))
    j = int(np.argmax(lls_f))
    return (float(fine[j]), float(lls_f[j])) if lls_f[j] >= lls[i] else (float(GRID[i]),
                                                                          float(lls[i]))


def missing_heat(result, nodes: tuple[str, ...] | None = None, say=None) -> MissingHeat:
    """Reconstruct the missing heat of a fitted model (`FitResult`) over its runs.

    `nodes`: the node names to report and to consider as carriers (default: every node
    of the model as written; a lowered lag's sensing element is never a carrier).
    """
    say = say or (lambda _m: None)
    names = list(result.lowered_spec.node_names)
    if nodes is None:
        made = {e.name for e in result.spec.effects if e.kind == "extra_node"}
        nodes = tuple(n for n in names if n in result.spec.node_names or n in made)
    idx = [names.index(n) for n in nodes]
    em = _ErrorModel(result)
    base = em.baseline()
    penalty = 0.5 * math.log(max(em.n_samples, 2))  # BIC per added carrier, in log L
    carriers: list[int] = []
    best_s, best_ll = 0.0, base
    remaining = list(idx)
    while remaining:
        trials = [(j, *_best_intensity(em, carriers + [j])) for j in remaining]
        j, s, ll = max(trials, key=lambda t: t[2])
        if not np.isfinite(ll) or ll - best_ll < penalty:  # the first one too
            break
        carriers.append(j)
        remaining.remove(j)
        best_s, best_ll = s, ll
        say(f"missing heat: {names[j]} carries a disturbance (log L +{ll - base:.1f})")
    out = MissingHeat(tuple(nodes), tuple(names[j] for j in carriers), best_s,
                      float(best_ll - base))
    n = len(names)
    for run, n_t in zip(em.runs, em.lengths):
        zs, var = (a[:n_t] for a in em.smooth(run, carriers, best_s))
        heat = np.zeros((n_t, len(nodes)))
        std = np.zeros_like(heat)
        for c, j in enumerate(carriers):
            col = idx.index(j)
            heat[:, col] = zs[:, n + c]
            std[:, col] = np.sqrt(np.maximum(var[:, n + c], 0.0))
        out.ts.append(run.ts[:n_t])
        out.heat.append(heat)
        out.heat_std.append(std)
        out.temperatures.append(run.x[:n_t, idx] + zs[:, idx])
    return out


def write_missing_heat(mh: MissingHeat, path: Path) -> None:
    """`stepK_missing_heat.csv` (docs/formats.md §3a): `time_s`, `run`, then
    `q_<node>_W` and `q_<node>_W_std` per node, one row per sample of every run."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    with tmp.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "run", *(c for n in mh.nodes for c in (f"q_{n}_W",
                                                                    f"q_{n}_W_std"))])
        for r, (ts, q, s) in enumerate(zip(mh.ts, mh.heat, mh.heat_std)):
            for k in range(len(ts)):
                w.writerow([repr(float(ts[k])), r, *(repr(float(v)) for pair in zip(q[k], s[k])
                                                     for v in pair)])
    tmp.replace(path)
