"""Each run's initial temperatures, estimated from the data by default.

A node the model file gives no `initial` (and not `initial = "steady"`) starts each run
where the data say: its start is a free parameter per run (`runs.<i>.nodes.<n>.initial`,
°C), as CTSM-R and pySIP hold x0 among the parameters. The estimate starts

- at the node's first finite reading in the run (the mean over its sensors), for a node
  a sensor reads;
- at the equilibrium of the model's linear part given those readings and the run's
  first input sample (`ThermalModel.initial_state`), for a node no sensor reads.

Nodes that effects add (an unmodelled mass, a sensor's own element) are not the user's
and hold no start of their own: they follow the equilibrium given the others. A node with
a written `initial` keeps it (fixed: set; bare: the start of the estimate, the same in
every run).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ..measurements._data import Experiment
from ..model._spec import ModelSpec, Parameter


def nodes_to_estimate(spec: ModelSpec) -> list[str]:
    """The nodes of `spec` whose initial temperature the data set: no `initial`, not
    `steady`, or a start taken from earlier data (`Node.initial_from_data`)."""
    return [n.name for n in spec.nodes
            if (n.initial is None and not n.steady) or n.initial_from_data]


def first_readings(spec: ModelSpec, sensor_columns, experiments: list[Experiment]
                   ) -> dict[str, np.ndarray]:
    """Per node that a sensor of `spec` reads: its first finite reading in each run
    (°C, shape (runs,), the mean over its sensors; NaN for a run where it has none).

    `sensor_columns`: the experiments' output columns in order."""
    columns = list(sensor_columns)
    out: dict[str, list[np.ndarray]] = {}
    for s in spec.sensors:
        j = columns.index(s.column)
        firsts = []
        for e in experiments:
            y = e.outputs[:, j]
            ok = np.flatnonzero(np.isfinite(y))
            firsts.append(float(y[ok[0]]) if ok.size else np.nan)
        out.setdefault(s.node, []).append(np.array(firsts))
    with warnings.catch_warnings():  # a run where none of a node's sensors reads
        warnings.simplefilter("ignore", RuntimeWarning)
        return {node: _fill(np.nanmean(np.stack(v), axis=0)) for node, v in out.items()}


def _fill(starts: np.ndarray) -> np.ndarray:
    """A run without a reading starts where the other runs do (on average)."""
    ok = np.isfinite(starts)
    return np.where(ok, starts, np.mean(starts[ok]) if ok.any() else np.nan)


def with_starts(spec: ModelSpec, starts: dict[str, np.ndarray]) -> ModelSpec:
    """`spec` with each node of `starts` given an estimated `initial` (the mean start
    over runs, marked as taken from the data)."""
    nodes = tuple(
        dataclasses.replace(n, initial=Parameter(float(np.mean(starts[n.name])), False),
                            initial_from_data=True) if n.name in starts else n
        for n in spec.nodes)
    return spec.replace(nodes=nodes)


def estimated_starts(lowered, experiments: list[Experiment], model_of) -> dict[str, np.ndarray]:
    """Per node of `lowered.original` to estimate (`nodes_to_estimate`), its start in
    each run (°C, shape (runs,)): the first reading where a sensor reads it, else the
    equilibrium of the linear part given those readings (and any written `initial`) at
    the run's first input sample (`conditional_equilibrium`).

    `experiments`: inputs in `lowered.spec`'s column order; `model_of(spec)`: the
    `ThermalModel` of a lowered spec."""
    todo = nodes_to_estimate(lowered.original)
    if not todo:
        return {}
    readings = first_readings(lowered.original, lowered.spec.sensor_columns, experiments)
    starts = {n: readings[n] for n in todo if n in readings and np.isfinite(readings[n]).all()}
    rest = [n for n in todo if n not in starts]
    if rest:
        spec = with_starts(lowered.spec, starts)
        model = model_of(spec)
        system = model.linear_system()
        A, B = np.asarray(system.A), np.asarray(system.B)
        pinned = np.array(model.initial_nodes, dtype=int)
        r0 = run_initial_start(spec, model, starts, len(experiments))
        x0 = np.stack([conditional_equilibrium(A, B, e.inputs[0], pinned, r)
                       for e, r in zip(experiments, r0)])
        names = spec.node_names
        starts.update({n: x0[:, names.index(n)] for n in rest})
    return starts


def conditional_equilibrium(A: np.ndarray, B: np.ndarray, u0: np.ndarray,
                            pinned: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The state (°C, shape (nodes,)) where `dx/dt = A x + B u0` is zero on every node
    but the `pinned` ones, which hold `values` (°C): an unmeasured mass next to a node
    that starts warm starts warm too. Without pinned nodes: the equilibrium."""
    n = A.shape[0]
    free = np.setdiff1d(np.arange(n), pinned)
    x = np.zeros(n)
    x[pinned] = values
    if free.size:
        rhs = -(B[free] @ u0) - A[np.ix_(free, pinned)] @ x[pinned]
        x[free] = np.linalg.solve(A[np.ix_(free, free)], rhs)
    return x


def run_initial_start(spec: ModelSpec, model, starts: dict[str, np.ndarray], n_runs: int
                      ) -> np.ndarray:
    """The `(runs, len(model.initial_nodes))` start of a fit's `run_initial` (°C): each
    node's per-run start where `starts` holds one, else its `initial`."""
    names = spec.node_names
    initial = np.asarray(model.initial)
    cols = [np.asarray(starts[names[i]], float) if names[i] in starts
            else np.full(n_runs, initial[i]) for i in model.initial_nodes]
    return np.stack(cols, axis=1) if cols else np.zeros((n_runs, 0))


#: Noise stds between the mean of a sensor's first three residuals and zero above which
#: `fit` warns that the run starts elsewhere than the model says (5 stds of that mean:
#: a fit that starts right never says it).
START_MISMATCH_STDS = 3.0


def start_mismatches(spec: ModelSpec, columns, noise: dict[str, float], predictions,
                     experiments: list[Experiment], n_first: int = 3) -> list[str]:
    """Warnings, one per run and sensor, where the mean of the first `n_first` measured
    residuals is more than `START_MISMATCH_STDS` noise stds (°C) off: the run starts
    where the model's initial state (written in the file, or `"steady"`) does not.

    `columns`: the sensor columns, in the order of `predictions`' outputs;
    `noise`: column -> fitted noise std; an experiment given as None is not checked (its
    start was estimated)."""
    out = []
    for r, (pred, e) in enumerate(zip(predictions, experiments)):
        if e is None:
            continue
        for j, col in enumerate(columns):
            res = e.outputs[:, j] - np.asarray(pred)[:, j]
            first = res[np.isfinite(res)][:n_first]
            sigma = noise.get(col)
            if not first.size or not sigma:
                continue
            off = float(np.mean(first))
            if abs(off) > START_MISMATCH_STDS * sigma:
                out.append(
                    f"{e.name}: the first readings of {col} are {off:+.3g} °C "
                    f"({abs(off) / sigma:.0f} noise stds) from the fitted model's start; the "
                    "initial temperatures the model file sets do not match this run. "
                    "Remove `initial` from the nodes (each run's start is then estimated) "
                    "or correct it.")
    return out


def fitted_starts(result) -> dict[str, np.ndarray]:
    """Node -> each run's estimated start (°C, (runs,)) of a `FitResult`, for the nodes
    of its file whose start the fit estimated."""
    names = result.lowered_spec.node_names
    run_initial = np.asarray(result.state.run_initial)
    estimated = set(nodes_to_estimate(result.spec))
    return {names[i]: run_initial[:, k] for k, i in enumerate(result.model.initial_nodes)
            if names[i] in estimated}
