"""A solved fit as a `FitResult`: values by name, uncertainty, metrics, smoothing.

The last stage of `fit`: `theta` goes back to physical values under the original
model's names (a structural effect's parameter by its effect name), fixed parameters
join with their file values, and the identifiability analysis, information criteria,
per-sensor metrics and (Kalman) smoothed node temperatures are added.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .._metrics import fit_metrics
from ..model._model import ThermalModel, model_to_spec
from ..model._spec import ModelSpec
from ..model.effects import Lowered, raise_effects
from ._identifiability import Identifiability, identifiability
from ._kalman_fit import kalman_smoothed
from ._problem import FitState, Prepared, Solution, _is_log, _Problem


@dataclass
class FitResult:
    """A fitted model with its evidence. Values are physical (J/K, W/K, °C, °C/√s)."""

    spec: ModelSpec  # the fitted model, as a file would hold it
    lowered_spec: ModelSpec  # the same with structural effects as plain entries (`model`'s)
    model: ThermalModel
    state: FitState
    likelihood: str
    parameters: dict[str, dict]  # dotted name -> {"value", "std", "free"}
    correlation: np.ndarray  # among the free parameters, in `free_names` order
    free_names: list[str]
    nll: float
    aic: float
    bic: float
    n_params: int
    n_samples: int
    rmse: dict[str, float]
    fit_percent: dict[str, float]
    per_run: list[dict]
    identifiability: Identifiability
    n_steps: int
    converged: bool
    message: str
    wall_time_s: float
    predictions: list[np.ndarray] = field(repr=False, default_factory=list)  # (times, outputs)
    # Kalman only: RTS-smoothed node temperatures per run, (times, nodes) mean and std (°C).
    smoothed: list[tuple[np.ndarray, np.ndarray]] = field(repr=False, default_factory=list)
    theta: np.ndarray | None = field(repr=False, default=None)
    problem: _Problem | None = field(repr=False, default=None)
    # Output error with the default solver: residual evaluations at trial points (each
    # of the `n_steps` iterations also evaluates residuals and Jacobian once).
    n_evaluations: int | None = None
    # Effect parameters fitted through a lowered entry: effect name -> (scale, power),
    # value = scale * lowered value ** power (e.g. a sensor lag's tau = C / G).
    lowered_as: dict[str, tuple[float, float]] = field(repr=False, default_factory=dict)


def summarize(prep: Prepared, sol: Solution, likelihood: str, t_start: float) -> FitResult:
    """The `FitResult` of a solved fit (`t_start`: `time.perf_counter()` at its start)."""
    spec, data = prep.spec, prep.data
    fitted_spec = model_to_spec(sol.state.model, spec, process_noise=likelihood == "kalman")
    ident = identifiability(sol.information, sol.names, fitted_spec,
                            sample_period=float(np.max(np.asarray(data.dt))))
    parameters = _parameters(sol, ident, spec)
    n_params = len(sol.names) + len(sol.noise)
    n_samples = int(np.asarray(data.mask).sum())
    predictions = [sol.predictions[r, :n] for r, n in enumerate(data.lengths)]
    metrics = fit_metrics(spec.sensor_columns, prep.experiments, predictions)
    smoothed = []
    if likelihood == "kalman":
        m_s, s_s = kalman_smoothed(sol.state.model, data, sol.state.run_initial)
        smoothed = [(np.asarray(m_s[r, :n]), np.asarray(s_s[r, :n]))
                    for r, n in enumerate(data.lengths)]
    renames = prep.lowered.renames()
    message = ("converged" if sol.converged
               else f"stopped after {sol.n_steps} steps without converging")
    return FitResult(
        spec=raise_effects(prep.lowered, fitted_spec), lowered_spec=fitted_spec,
        model=sol.state.model, state=sol.state, likelihood=likelihood,
        parameters=_raise_names(parameters, prep.lowered), correlation=_correlation(ident),
        free_names=[renames[n][0] if n in renames else n for n in sol.names], nll=sol.nll,
        aic=2 * n_params + 2 * sol.nll, bic=n_params * math.log(n_samples) + 2 * sol.nll,
        n_params=n_params, n_samples=n_samples, rmse=metrics["rmse"],
        fit_percent=metrics["fit_percent"], per_run=metrics["per_run"],
        identifiability=_rename_identifiability(ident, {k: v[0] for k, v in renames.items()}),
        n_steps=sol.n_steps, converged=sol.converged, message=message,
        n_evaluations=sol.n_evaluations, wall_time_s=time.perf_counter() - t_start, predictions=predictions,
        smoothed=smoothed, theta=sol.theta, problem=sol.problem,
        lowered_as={target: (scale, power) for target, scale, power in renames.values()})


def _parameters(sol: Solution, ident: Identifiability, spec: ModelSpec) -> dict[str, dict]:
    """Every parameter by dotted name (lowered spec): free ones from `theta` with their
    std (None where unidentifiable), the noise stds, then the fixed ones."""
    stds = (np.sqrt(np.clip(np.diag(ident.covariance), 0, None)) if ident.stds is None
            else ident.stds)
    out: dict[str, dict] = {}
    for j, name in enumerate(sol.names):
        log = _is_log(name)
        v = float(np.exp(sol.theta[j])) if log else float(sol.theta[j])
        sd = None
        if name not in ident.unidentifiable_parameters and np.isfinite(stds[j]):
            sd = float(v * stds[j]) if log else float(stds[j])
        out[name] = {"value": v, "std": sd, "free": True}
    for name, (v, sd) in sol.noise.items():
        out[name] = {"value": v, "std": sd, "free": True}
    _add_fixed_parameters(out, spec)
    return out


def _correlation(ident: Identifiability) -> np.ndarray:
    cov = ident.covariance
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return cov / d[:, None] / d[None, :]


def _add_fixed_parameters(parameters: dict, spec: ModelSpec) -> None:
    """Fixed parameters appear in the report too, with their file values and std None."""
    entries = [(f"nodes.{n.name}.capacitance", n.capacitance) for n in spec.nodes]
    entries += [(f"links.{k.key}.conductance", k.conductance) for k in spec.links]
    entries += [(f"boundaries.{b.key}.conductance", b.conductance) for b in spec.boundaries]
    entries += [(f"heat_inputs.{h.key}.gain", h.gain) for h in spec.heat_inputs]
    entries += [(f"sensors.{s.column}.noise", s.noise) for s in spec.sensors]
    entries += [(f"nodes.{n.name}.initial", n.initial) for n in spec.nodes]
    for name, p in entries:
        if name not in parameters and p is not None and p.fixed:
            parameters[name] = {"value": float(p.value), "std": None, "free": False}


def _raise_names(parameters: dict, lowered: Lowered) -> dict:
    """Report entries under the original model's names: a structural effect's parameter
    by its effect name (`effects.<kind>.<where>.<parameter>`), and nothing of the helper
    entries lowering made (a sensor element's fixed mass)."""
    renames = lowered.renames()
    new_nodes = set(lowered.spec.node_names) - set(lowered.original.node_names)
    out = {}
    for name, entry in parameters.items():
        if name in renames:
            target, scale, power = renames[name]
            v = scale * entry["value"] ** power
            sd = None if entry["std"] is None else abs(power) * v * entry["std"] / entry["value"]
            out[target] = {**entry, "value": v, "std": sd}
        elif not new_nodes & set(name.replace("-", ".").split(".")):
            out[name] = entry
    return out


def _rename_identifiability(ident: Identifiability, renames: dict[str, str]) -> Identifiability:
    """The identifiability report under the original model's names (see `_raise_names`)."""
    if not renames:
        return ident
    order = sorted(renames, key=len, reverse=True)

    def rename(x):
        if isinstance(x, str):
            for old in order:
                x = x.replace(old, renames[old])
            return x
        if isinstance(x, list):
            return [rename(v) for v in x]
        if isinstance(x, dict):
            return {k: rename(v) for k, v in x.items()}
        return x

    return dataclasses.replace(ident, directions=[rename(d) for d in ident.directions],
                               unidentifiable_parameters={
                                   rename(n) for n in ident.unidentifiable_parameters})
