"""Observability of a sampled thermal network: rank, Gramian and weak states in words.

The observer runs on the sampled system `x[k+1] = Phi x[k] + ...`, `y[k] = C x[k] + v[k]`
with sensor noise `v ~ N(0, R)`, `R = diag(noise²)`. Two figures describe how well the
readings determine the state:

- the **observability matrix** `O = [C; C Phi; ...; C Phi^(n-1)]` and its rank: full
  rank (`n`) or not is a yes/no answer. Its *condition number* is not a useful figure:
  it grows like `‖Phi‖ⁿ` (or `‖A‖ⁿ` in continuous time, 1e10 and beyond for a stiff
  six-node network) and says more about the units of time than about the sensors.
- the **discrete observability Gramian** over a horizon of `N` samples,

  `W_N = Σ_{k=0}^{N-1} (Phiᵀ)^k Cᵀ R⁻¹ C Phi^k`  (1/°C² · °C² = dimensionless per sample),

  the Fisher information about the initial state `x[0]` carried by `N` noisy readings.
  Its eigenvalues `μ` are the figures that matter: `1/√μ` (°C) is the standard
  deviation with which the horizon's data pin the initial-state combination along
  the eigenvector; `cond(W_N) = μ_max/μ_min` measures how unevenly the sensors see the
  state, `μ_min` the worst direction, `log det W_N` the volume (D-optimality). With
  `N = ∞` (`horizon=None`) it solves `W = Phiᵀ W Phi + Cᵀ R⁻¹ C` (Phi stable).

A weakly observable direction is not necessarily a problem for an observer: a mode
that decays fast on its own (the proof mass of the six-node IMU, time constant 0.09 s)
is *detectable*, its estimation error dies without correction. The messages say so.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from .._errors import InputError

DEFAULT_HORIZON = 600.0  # s: two time constants of the slowest (enclosure) mode of imu6
DEFAULT_MAX_STD = 0.1  # °C: a direction pinned worse than this over the horizon is weak


def observability_matrix(system) -> np.ndarray:
    """The observability matrix `[C; C F; ...; C F^(n-1)]` of a system.

    `F` is `system.Phi` for a `DiscreteSystem` and `system.A` for a `LinearSystem`.
    Use it for the rank only: its condition number grows like `‖F‖ⁿ` and misleads
    (see `observability_gramian`).

    **Arguments:**

    - `system`: a `DiscreteSystem` or `LinearSystem`.

    **Returns:** a NumPy array of shape `(n·outputs, n)`.
    """
    F, C = _state_matrix(system), np.asarray(system.C, float)
    n = F.shape[0]
    blocks, block = [], C
    for _ in range(n):
        blocks.append(block)
        block = block @ F
    return np.concatenate(blocks, axis=0)


def observability_rank(system, rtol: float = 1e-10) -> int:
    """The rank of the observability Gramian-equivalent test: the number of singular values
    of the row-scaled observability matrix above `rtol` times the largest.

    Each block `C F^k` is scaled to unit norm first, so the stiff decay of `F^k` does
    not hide directions (the raw matrix's singular values span `‖F‖ⁿ`).

    **Arguments:**

    - `system`: a `DiscreteSystem` or `LinearSystem`.
    - `rtol`: relative singular-value threshold.

    **Returns:** an integer in `[0, n]`; `n` means observable.
    """
    F, C = _state_matrix(system), np.asarray(system.C, float)
    n = F.shape[0]
    blocks, block = [], C
    for _ in range(n):
        norm = np.linalg.norm(block)
        blocks.append(block / norm if norm > 0 else block)
        block = block @ F
    s = np.linalg.svd(np.concatenate(blocks, axis=0), compute_uv=False)
    return int(np.sum(s > rtol * max(s.max(initial=0.0), 1e-300)))


def observability_gramian(system, horizon: float | None = DEFAULT_HORIZON,
                          noise=None) -> np.ndarray:
    """The discrete observability Gramian `W_N = Σ_{k<N} (Phiᵀ)^k Cᵀ R⁻¹ C Phi^k`.

    `N = round(horizon / dt)` samples (the readings `y[0..N-1]`), `R = diag(noise²)`.
    Its condition number (not the observability matrix's, which grows like `‖A‖ⁿ`)
    is the figure that says how evenly the sensors see the state; `1/√μ_min` (°C) is
    the std of the worst-determined initial-state combination from the horizon's data.
    Evaluated by doubling (`W_{a+b} = W_a + (Phi^a)ᵀ W_b Phi^a`): `O(n³ log N)`.

    **Arguments:**

    - `system`: a `DiscreteSystem` (states × states `Phi`, outputs × states `C`, `dt`).
    - `horizon`: seconds of data; `None` for the infinite horizon (discrete Lyapunov
      equation, needs `Phi` stable).
    - `noise`: sensor noise std per output (°C), shape (outputs,); default 1 (then `W`
      is per unit noise).

    **Returns:** the symmetric Gramian, shape (states, states), in 1/°C² × °C² per sample.
    """
    Phi, C = _state_matrix(system), np.asarray(system.C, float)
    M = _information(C, noise)
    if horizon is None:
        if np.max(np.abs(np.linalg.eigvals(Phi)), initial=0.0) >= 1.0:
            raise ValueError("`observability_gramian(horizon=None)` needs a stable `Phi` for "
                             "the infinite horizon; give a finite horizon in seconds.")
        W = scipy.linalg.solve_discrete_lyapunov(Phi.T, M)
    else:
        dt = float(system.dt)
        steps = int(round(float(horizon) / dt))
        if steps < 1:
            raise ValueError(f"`observability_gramian(horizon={horizon})` covers no sample at "
                             f"dt = {dt:g} s; give at least one sample period.")
        W = gramian_steps(Phi, M, steps)
    return 0.5 * (W + W.T)


def gramian_steps(Phi: np.ndarray, M: np.ndarray, steps: int) -> np.ndarray:
    """`Σ_{k<steps} (Phiᵀ)^k M Phi^k` by binary doubling (exact, `O(n³ log steps)`)."""
    n = Phi.shape[0]
    W = np.zeros((n, n))
    shift = np.eye(n)  # Phi^a for the a steps accumulated so far
    G, P = M.copy(), Phi.copy()  # W_{2^j}, Phi^{2^j}
    while steps:
        if steps & 1:
            W = W + shift.T @ G @ shift
            shift = P @ shift
        steps >>= 1
        if steps:
            G = G + P.T @ G @ P
            P = P @ P
    return W


@dataclass
class Observability:
    """What a set of sensors can tell about a sampled network's state.

    - `rank`: rank of the observability matrix (`n` = observable).
    - `gramian`: `W_N` (see `observability_gramian`), `horizon` its span (s, `None` = ∞).
    - `eigenvalues`: of `W_N`, ascending; `condition_number = μ_max/μ_min` (the figure
      that matters), `min_eigenvalue`, `logdet`, `worst_std = 1/√μ_min` (°C).
    - `matrix_condition_number`: of the raw observability matrix, for comparison only
      (it grows like `‖Phi‖ⁿ` and misleads).
    - `min_time_constant`, `modes`: when set, `gramian` is over the `modes` slow modes
      only (see `observability`).
    - `weak`: one entry per weakly observable group of nodes, with `nodes`, `std`,
      `restore` (the node whose sensor best restores it) and the plain-words `message`.
    """

    sensors: tuple[str, ...]
    state_names: tuple[str, ...]
    rank: int
    horizon: float | None
    dt: float
    gramian: np.ndarray
    eigenvalues: np.ndarray
    matrix_condition_number: float
    weak: list[dict] = field(default_factory=list)
    min_time_constant: float | None = None  # s: faster modes projected out of `gramian`
    modes: int | None = None  # the Gramian's dimension (modes kept)

    @property
    def observable(self) -> bool:
        return self.rank == len(self.state_names)

    @property
    def condition_number(self) -> float:
        mu = self.eigenvalues
        return float(mu[-1] / mu[0]) if mu[0] > 0 else math.inf

    @property
    def min_eigenvalue(self) -> float:
        return float(self.eigenvalues[0])

    @property
    def logdet(self) -> float:
        mu = self.eigenvalues
        return float(np.sum(np.log(mu))) if mu[0] > 0 else -math.inf

    @property
    def worst_std(self) -> float:
        mu0 = self.eigenvalues[0]
        return float(1.0 / math.sqrt(mu0)) if mu0 > 0 else math.inf

    @property
    def messages(self) -> list[str]:
        return [w["message"] for w in self.weak]

    def to_json(self) -> dict:
        def finite(x):
            return float(x) if math.isfinite(x) else None
        return {"sensors": list(self.sensors), "rank": self.rank, "states": len(self.state_names),
                "horizon_s": self.horizon, "dt_s": self.dt,
                "min_time_constant_s": self.min_time_constant, "modes": self.modes,
                "gramian_condition_number": finite(self.condition_number),
                "gramian_min_eigenvalue": self.min_eigenvalue,
                "gramian_logdet": finite(self.logdet), "worst_std_C": finite(self.worst_std),
                "observability_matrix_condition_number": finite(self.matrix_condition_number),
                "weak": [{k: v for k, v in w.items()} for w in self.weak]}


def observability(network, dt: float, sensors=None, horizon: float | None = DEFAULT_HORIZON,
                  noise=None, max_std: float = DEFAULT_MAX_STD,
                  min_time_constant: float | None = None) -> Observability:
    """How well sensors on some nodes of a thermal network determine all its temperatures.

    Samples the network at `dt`, builds the Gramian `W_N` of the sensor set over the
    horizon, and explains each weakly observable direction (its initial-state std
    `1/√μ` over `max_std`, or `μ` numerically zero) in words: which nodes, why (no
    conduction path to a sensor; a node that settles onto its neighbours within a few
    samples; a weak coupling), and which extra sensor would restore them.

    **Arguments:**

    - `network`: a `ThermalNetwork` or a `ThermalModel` (then the default noise is the
      model's sensor noise).
    - `dt`: observer sample period (s).
    - `sensors`: node names or indices carrying a sensor (each reads its node's
      temperature); default the network's own sensors.
    - `horizon`: seconds of data in the Gramian; `None` for the infinite horizon.
    - `noise`: sensor noise std (°C), a scalar or one per sensor; default the model's,
      else 0.01 °C.
    - `max_std`: a direction known worse than this (°C) from the horizon's data is weak.
    - `min_time_constant`: if given (s), the Gramian is restricted to the thermal modes
      with open-loop time constant at least this long, `W_slow = Pᵀ W P` with `P` their
      mode shapes (each scaled to 1 °C at its largest node). Faster modes decay on their
      own (detectable) and an observer keeps their poles (`observer_poles` with the
      same `min_time_constant`), so their tiny `μ` would otherwise dominate
      `cond(W)` and hide how well the sensors see the modes that matter.

    **Returns:** an `Observability`.
    """
    view = NetworkView.of(network)
    nodes = view.resolve(sensors, "observability")
    noise = view.noise_for(nodes, noise)
    basis = view.slow_basis(min_time_constant)
    per_node = [basis.T @ W @ basis for W in view.node_gramians(dt, horizon)]
    W = sum(per_node[i] / s ** 2 for i, s in zip(nodes, noise))
    system = view.discrete(dt, nodes)
    rank = observability_rank(system)
    mu = np.linalg.eigvalsh(W)
    mu = np.maximum(mu, 0.0)
    O = observability_matrix(system)
    sv = np.linalg.svd(O, compute_uv=False)
    mcond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    weak = _weak_groups(W, basis, view, nodes, per_node, dt, max_std, noise)
    return Observability(tuple(view.names[i] for i in nodes), view.names, rank, horizon,
                         float(dt), W, mu, mcond, weak, min_time_constant, basis.shape[1])


@dataclass(frozen=True)
class NetworkView:
    """NumPy facts about a network the observer design needs (names, couplings, matrices)."""

    names: tuple[str, ...]
    A: np.ndarray
    capacitance: np.ndarray
    conductance: np.ndarray  # node × node link conductances (W/K), zero diagonal
    boundary: np.ndarray  # per node, boundary conductance (W/K)
    sensor_nodes: tuple[int, ...]
    sensor_noise: np.ndarray | None
    network: object

    @classmethod
    def of(cls, network) -> "NetworkView":
        from ..model._model import ThermalModel
        from ..model._network import ThermalNetwork

        noise = None
        if isinstance(network, ThermalModel):
            noise = np.asarray(network.noise, float)
            network = network.network
        if not isinstance(network, ThermalNetwork):
            raise TypeError("`observability(network=...)` needs a `ThermalNetwork` or "
                            f"`ThermalModel`, got {type(network).__name__}.")
        t = network.topology
        n = t.n_nodes
        G = np.zeros((n, n))
        for (i, j), g in zip(t.links, np.asarray(network.conductance, float)):
            G[i, j] += g
            G[j, i] += g
        b = np.zeros(n)
        for i, g in zip(t.boundary_nodes, np.asarray(network.boundary_conductance, float)):
            b[i] += g
        system = network.linear_system()
        return cls(t.node_names, np.asarray(system.A, float),
                   np.asarray(network.capacitance, float), G, b, t.sensor_nodes, noise, network)

    @property
    def n(self) -> int:
        return len(self.names)

    def resolve(self, sensors, call: str) -> tuple[int, ...]:
        """Node indices for names or indices; default the network's sensors."""
        if sensors is None:
            return tuple(self.sensor_nodes)
        out = []
        for s in sensors:
            if isinstance(s, str):
                if s not in self.names:
                    raise InputError(f"`{call}(sensors=...)` names node '{s}', but the network's "
                                     f"nodes are {list(self.names)}.")
                out.append(self.names.index(s))
            else:
                i = int(s)
                if not 0 <= i < self.n:
                    raise InputError(f"`{call}(sensors=...)` refers to node {i}, but only "
                                     f"{self.n} nodes were given. Node indices are 0-based.")
                out.append(i)
        if len(set(out)) != len(out):
            raise InputError(f"`{call}(sensors=...)` lists a node twice: {list(sensors)}.")
        return tuple(out)

    def noise_for(self, nodes, noise) -> np.ndarray:
        if noise is None:
            if self.sensor_noise is not None:
                by_node = dict(zip(self.sensor_nodes, self.sensor_noise))
                default = float(np.median(self.sensor_noise))
                return np.array([by_node.get(i, default) for i in nodes], float)
            from ..model._model import DEFAULT_NOISE
            noise = DEFAULT_NOISE
        noise = np.broadcast_to(np.asarray(noise, float), (len(nodes),)).copy()
        if not np.all(noise > 0):
            raise InputError(f"sensor noise must be > 0 (std, °C), got {noise}.")
        return noise

    def discrete_phi(self, dt: float) -> np.ndarray:
        return scipy.linalg.expm(self.A * float(dt))

    def discrete(self, dt: float, nodes):
        from ..model._system import DiscreteSystem

        C = np.zeros((len(nodes), self.n))
        C[np.arange(len(nodes)), list(nodes)] = 1.0
        z = np.zeros((self.n, 0))
        return DiscreteSystem(self.discrete_phi(dt), z, z, C, np.zeros((len(nodes), 0)),
                              np.asarray(float(dt)))

    def node_gramians(self, dt: float, horizon: float | None) -> list[np.ndarray]:
        """Per node `i`, the Gramian of a unit-noise sensor reading node `i`."""
        Phi = self.discrete_phi(dt)
        out = []
        for i in range(self.n):
            M = np.zeros((self.n, self.n))
            M[i, i] = 1.0
            if horizon is None:
                W = scipy.linalg.solve_discrete_lyapunov(Phi.T, M)
            else:
                steps = int(round(float(horizon) / float(dt)))
                if steps < 1:
                    raise InputError(f"`observability(horizon={horizon})` covers no sample at "
                                     f"dt = {dt:g} s.")
                W = gramian_steps(Phi, M, steps)
            out.append(0.5 * (W + W.T))
        return out

    def slow_basis(self, min_time_constant: float | None) -> np.ndarray:
        """Mode shapes (columns, 1 °C at their largest node) of the modes with time constant
        `>= min_time_constant` (s), slowest first; the identity when `None`."""
        if min_time_constant is None:
            return np.eye(self.n)
        lam, P = scipy.linalg.eig(self.A)
        lam, P = lam.real, P.real
        order = np.argsort(-lam)  # slowest first
        lam, P = lam[order], P[:, order]
        keep = -1.0 / lam >= float(min_time_constant)
        if not keep.any():
            raise InputError(f"`observability(min_time_constant={min_time_constant})` leaves "
                             f"no mode: the slowest time constant is {-1 / lam[0]:.3g} s.")
        P = P[:, keep]
        P = P / P[np.argmax(np.abs(P), axis=0), np.arange(P.shape[1])][None, :]
        return P

    def local_time_constant(self, i: int) -> float:
        """`C_i / (Σ_j G_ij + g_b,i)` (s): how fast node `i` settles onto its neighbours."""
        total = self.conductance[i].sum() + self.boundary[i]
        return float(self.capacitance[i] / total) if total > 0 else math.inf

    def path_to(self, i: int, targets) -> list[int] | None:
        """Shortest link path from node `i` to any of `targets` (breadth first), or None."""
        targets = set(targets)
        prev = {i: None}
        queue = deque([i])
        while queue:
            a = queue.popleft()
            if a in targets:
                path = [a]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return path[::-1]
            for b in np.flatnonzero(self.conductance[a] > 0):
                if int(b) not in prev:
                    prev[int(b)] = a
                    queue.append(int(b))
        return None


def _weak_groups(W, basis, view: NetworkView, nodes, per_node, dt, max_std, noise
                 ) -> list[dict]:
    """The weak eigen-directions of `W` (in the coordinates of `basis`), grouped by shared
    nodes, each explained."""
    mu, V = np.linalg.eigh(W)
    mu_max = max(float(mu[-1]), 1e-300)
    null = mu <= 1e-13 * mu_max
    weak = null | (1.0 / np.sqrt(np.maximum(mu, 1e-300)) > max_std)
    groups: list[dict] = []
    for j in np.flatnonzero(weak):
        shape = basis @ V[:, j]  # the direction as node temperatures
        v = shape / np.max(np.abs(shape))
        members = {int(i) for i in np.flatnonzero(np.abs(v) >= 0.3)}
        touching = [g for g in groups if g["members"] & members]
        merged = {"members": members.union(*[g["members"] for g in touching]),
                  "columns": [j] + [c for g in touching for c in g["columns"]]}
        groups = [g for g in groups if g not in touching] + [merged]
    noise_default = float(np.median(noise)) if len(noise) else 0.01
    out = []
    for g in groups:
        cols = sorted(g["columns"])
        Vg = V[:, cols]
        std = float(1.0 / np.sqrt(max(mu[cols[0]], 1e-300)))
        lost = bool(null[cols].any())
        # The extra sensor that best restores this subspace: largest smallest eigenvalue of
        # W restricted to it, after adding that node's Gramian.
        best, best_std = None, std
        for c in range(view.n):
            if c in nodes:
                continue
            Wc = Vg.T @ (W + per_node[c] / noise_default ** 2) @ Vg
            s = float(1.0 / np.sqrt(max(np.linalg.eigvalsh(Wc)[0], 1e-300)))
            if s < best_std:
                best, best_std = c, s
        names = [view.names[i] for i in sorted(g["members"])]
        entry = {"nodes": names, "dimension": len(cols), "std": None if lost else std,
                 "unobservable": lost,
                 "restore": None if best is None else view.names[best],
                 "restored_std": None if best is None else best_std}
        entry["message"] = _explain(entry, sorted(g["members"]), view, nodes, dt)
        out.append(entry)
    return out


def _explain(entry, members, view: NetworkView, nodes, dt) -> str:
    names = ", ".join(entry["nodes"])
    if entry["unobservable"]:
        text = (f"The temperature of {names} cannot be determined from the sensors on "
                f"{', '.join(view.names[i] for i in nodes) or 'no node'} (unobservable, "
                f"{entry['dimension']} direction(s)).")
    else:
        text = (f"The temperature of {names} is weakly observable: {entry['std']:.3g} °C "
                f"std for the worst combination from the horizon's readings.")
    reasons = []
    for i in members:
        if i in nodes:
            continue
        path = view.path_to(i, nodes)
        tau = view.local_time_constant(i)
        if path is None:
            reasons.append(f"{view.names[i]} has no conduction path to any sensor, so its "
                           "temperature never reaches a reading")
        elif tau < 5 * dt:
            reasons.append(f"{view.names[i]} settles onto its neighbours with a local time "
                           f"constant of {tau:.2g} s ({tau / dt:.2g} samples at dt = {dt:g} s): "
                           "its own temperature leaves almost no trace in the readings, but an "
                           "error in it also dies out on its own within that time (the mode is "
                           "detectable), so an observer need not correct it")
        else:
            g = min(view.conductance[a, b] for a, b in zip(path[:-1], path[1:])) \
                if len(path) > 1 else math.inf
            route = " → ".join(view.names[k] for k in path)
            reasons.append(f"{view.names[i]} reaches a sensor only through {route} (weakest "
                           f"link {g:.3g} W/K against {view.capacitance[i]:.3g} J/K), so its heat "
                           "barely shows in the readings")
    if not reasons and len(members) > 1:
        reasons.append("the sensed nodes see these nodes only through the same couplings, so "
                       "only a combination of their temperatures shows")
    if reasons:
        text += " Why: " + "; ".join(reasons) + "."
    if entry["restore"] is not None:
        if entry["unobservable"]:
            text += f" A sensor on {entry['restore']} would restore it"
        else:
            text += f" A sensor on {entry['restore']} would restore it best"
        text += f" ({entry['restored_std']:.3g} °C std)."
    return text


def _state_matrix(system) -> np.ndarray:
    F = getattr(system, "Phi", None)
    if F is None:
        F = getattr(system, "A", None)
    if F is None:
        raise TypeError("expected a `DiscreteSystem` (with `Phi`) or a `LinearSystem` (with "
                        f"`A`), got {type(system).__name__}.")
    return np.asarray(F, float)


def _information(C: np.ndarray, noise) -> np.ndarray:
    if noise is None:
        return C.T @ C
    noise = np.broadcast_to(np.asarray(noise, float), (C.shape[0],))
    if not np.all(noise > 0):
        raise ValueError(f"`observability_gramian(noise=...)` needs positive stds, got {noise}.")
    Cw = C / noise[:, None]
    return Cw.T @ Cw
