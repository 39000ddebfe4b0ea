"""Sensor placement: the best `k` sensors among candidate nodes, by Gramian conditioning."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from ._observability import DEFAULT_HORIZON, NetworkView

CRITERIA = ("condition", "min_eigenvalue", "logdet")


@dataclass(frozen=True)
class SensorSet:
    """One candidate sensor set and its Gramian figures (see `observability_gramian`).

    - `nodes`: node names carrying a sensor.
    - `condition_number`: `μ_max/μ_min` of `W_N` (∞ when unobservable).
    - `min_eigenvalue`: `μ_min` (per sample, noise-weighted); `worst_std = 1/√μ_min` (°C).
    - `logdet`: `log det W_N` (−∞ when unobservable).
    - `rank`: numerical rank of `W_N` (`μ > 1e-13 μ_max`).
    """

    nodes: tuple[str, ...]
    condition_number: float
    min_eigenvalue: float
    logdet: float
    rank: int

    @property
    def worst_std(self) -> float:
        return 1.0 / math.sqrt(self.min_eigenvalue) if self.min_eigenvalue > 0 else math.inf


def sensor_set_figures(W: np.ndarray, names: tuple[str, ...]) -> SensorSet:
    """The `SensorSet` figures of a Gramian `W` (states × states)."""
    mu = np.linalg.eigvalsh(0.5 * (W + W.T))
    mu_max = max(float(mu[-1]), 1e-300)
    rank = int(np.sum(mu > 1e-13 * mu_max))
    full = rank == len(mu)
    return SensorSet(tuple(names), float(mu[-1] / mu[0]) if full else math.inf,
                     float(max(mu[0], 0.0)), float(np.sum(np.log(mu))) if full else -math.inf,
                     rank)


def _score(s: SensorSet, criterion: str) -> tuple:
    """Sort key, smaller is better: observable sets first (higher rank), then the criterion."""
    if criterion == "condition":
        value = s.condition_number
    elif criterion == "min_eigenvalue":
        value = -s.min_eigenvalue
    else:
        value = -s.logdet
    return (-s.rank, value)


def sensor_placement(network, k: int, dt: float, candidates=None, required=(),
                     horizon: float | None = DEFAULT_HORIZON, noise: float | None = None,
                     criterion: str = "condition", max_exhaustive: int = 20_000,
                     min_time_constant: float | None = None) -> list[SensorSet]:
    """The best `k` sensor nodes among `candidates`, ranked by the observability Gramian.

    Each set `S` is scored on `W_S = Σ_{i∈S} W_i / σ²`, with `W_i` the Gramian of a
    sensor reading node `i` over `horizon` (see `observability_gramian`). Sets that
    leave a state unobservable rank last. The `criterion` among observable sets:

    - `"condition"` (default): smallest `cond(W_S) = μ_max/μ_min`, how evenly the
      sensors see every direction. Not monotone: adding a sensor
      can worsen it by raising `μ_max`.
    - `"min_eigenvalue"`: largest `μ_min` (E-optimal): the worst direction's std
      `1/√μ_min` is smallest. Monotone in the set.
    - `"logdet"`: largest `log det W_S` (D-optimal): smallest uncertainty volume.

    Exhaustive over all `C(len(candidates), k)` sets when there are at most
    `max_exhaustive`; greedy beyond (add the node that best improves the criterion, one
    at a time; returns the greedy path's final set and the runners-up of the last step).

    **Arguments:**

    - `network`: a `ThermalNetwork` or `ThermalModel`.
    - `k`: number of sensors to place (counting `required`).
    - `dt`: observer sample period (s).
    - `candidates`: node names or indices allowed to carry a sensor; default all nodes.
    - `required`: nodes that carry a sensor in every set (e.g. an on-die sensor).
    - `horizon`: seconds in the Gramian; `None` for infinite.
    - `noise`: sensor noise std (°C), the same for every sensor; default the model's
      median, else 0.01 °C. It scales `W` and so `min_eigenvalue` and `logdet` only.
    - `criterion`: `"condition"`, `"min_eigenvalue"` or `"logdet"`.
    - `max_exhaustive`: the largest number of sets searched exhaustively.
    - `min_time_constant`: if given (s), score on the Gramian of the modes at least this
      slow only (see `observability`): modes faster than the observer decay on their own.

    **Returns:** `SensorSet`s, best first (all sets when exhaustive).
    """
    if criterion not in CRITERIA:
        raise InputError(f"`sensor_placement(criterion={criterion!r})` must be one of "
                         f"{list(CRITERIA)}.")
    view = NetworkView.of(network)
    cand = view.resolve(range(view.n) if candidates is None else candidates, "sensor_placement")
    req = view.resolve(required, "sensor_placement") if required else ()
    cand = tuple(c for c in cand if c not in req)
    free = k - len(req)
    if free < 0 or free > len(cand):
        raise InputError(f"`sensor_placement(k={k})` must lie between the {len(req)} required "
                         f"sensors and {len(req) + len(cand)} (required plus candidates).")
    sigma = float(view.noise_for((0,), noise)[0])
    basis = view.slow_basis(min_time_constant)
    r = basis.shape[1]
    per_node = [basis.T @ W @ basis / sigma ** 2 for W in view.node_gramians(dt, horizon)]
    base = sum((per_node[i] for i in req), np.zeros((r, r)))

    def figures(extra):
        nodes = (*req, *extra)
        W = base + sum((per_node[i] for i in extra), np.zeros((r, r)))
        return sensor_set_figures(W, tuple(view.names[i] for i in nodes))

    if math.comb(len(cand), free) <= max_exhaustive:
        sets = [figures(c) for c in itertools.combinations(cand, free)]
        return sorted(sets, key=lambda s: _score(s, criterion))
    chosen: list[int] = []
    last = []
    for _ in range(free):
        last = sorted(((figures((*chosen, c)), c) for c in cand if c not in chosen),
                      key=lambda sc: _score(sc[0], criterion))
        chosen.append(last[0][1])
    return [s for s, _ in last]
