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

import numpy as np

from .._errors import InputError
from ._metrics import fit_metrics, fit_percent, rmse
from ..model._model import model_to_spec
from ..model._spec import ModelSpec, Parameter
from ..model.effects import Lowered, raise_effects
from ._bias import BiasFit, bias_fit_at, bias_parameters, bias_to_spec, fit_bias
from ._bias_residuals import node_temperatures, spec_strains
from ._dominance import dominance_message, dominant_samples
from ._fit_result import FitResult
from ._output_error import bias_coefficient_jacobian
from ._identifiability import Identifiability, identifiability
from ._twin_optima import with_twin_optima
from ._problem import Prepared, Solution, _is_log


def _check_finite_information(information, names) -> None:
    """Raise an `InputError` naming the parameters whose sensitivities are not finite at
    the fitted values (`information`: (P, P); `names`: P)."""
    bad = ~np.all(np.isfinite(np.asarray(information, float)), axis=1)
    if bad.any():
        which = ("every parameter" if bad.all() else
                 ", ".join(n for n, b in zip(names, bad) if b))
        raise InputError(
            f"the sensitivities of {which} are not finite at the fitted values: an expression is undefined or "
            "infinitely steep where the data go (abs(x)^n or x^n with n < 0 at x = 0, "
            "log or 1/x of a value reaching 0); write it so it stays finite there, or "
            "fix those parameters")


def summarize(prep: Prepared, sol: Solution, likelihood: str, t_start: float) -> FitResult:
    """The `FitResult` of a solved fit (`t_start`: `time.perf_counter()` at its start)."""
    spec, data = prep.spec, prep.data
    fitted_spec = model_to_spec(sol.state.model, spec, process_noise=likelihood == "kalman")
    heat = [spec.input_columns.index(c) for c in spec.heat_columns]
    _check_finite_information(sol.information, sol.names)
    ident = identifiability(sol.information, sol.names, fitted_spec,
                            sample_period=float(np.max(np.asarray(data.dt))),
                            powered=bool(heat) and bool(np.any(
                                np.asarray(data.inputs)[:, :, heat] != 0)))
    if sol.alternatives:
        ident = with_twin_optima(ident, sol.names, sol.theta, sol.nll, sol.alternatives)
    parameters = _parameters(sol, ident, spec)
    n_params = len(sol.names) + len(sol.noise)
    n_samples = int(np.asarray(data.mask).sum())
    predictions = [sol.predictions[r, :n] for r, n in enumerate(data.lengths)]
    metrics = fit_metrics(spec.sensor_columns, prep.experiments, predictions)
    biases = _bias_fits(prep, sol, likelihood, ident)
    nll = sol.nll
    for column, b in biases.items():
        for name, entry in bias_parameters(b).items():
            parameters.setdefault(name, entry)  # τ and σ of a joint fit keep their stds
        # output error: τ's and σ are counted in theta and noise, the coefficients here;
        # Kalman: the bias channel is fitted after the filter, all of it counts here.
        n_params += b.n_params if likelihood == "kalman" else len(b.names) - len(
            [n for n in b.names if n in b.fixed])
        nll += b.nll if likelihood == "kalman" else 0.0
        n_samples += int(sum(np.isfinite(r).sum() for r in b.residuals))
        _add_bias_metrics(metrics, b)
        fitted_spec = _with_bias(fitted_spec, b)
    renames = prep.lowered.renames()
    in_fit = [dataclasses.replace(e, outputs=np.where(
        np.asarray(data.mask)[r, :e.n_times], e.outputs, np.nan))
        for r, e in enumerate(prep.experiments)]  # a held-out run counts no sample
    dominant = dominant_samples(spec.sensor_columns, in_fit, predictions)
    converged = sol.converged and not dominant and not sol.not_stationary
    # short of a stationary point, samples that seem to dominate are a symptom of it
    message = (f"not converged: {sol.not_stationary}" if sol.not_stationary
               else dominance_message(dominant) if dominant
               else "converged" if sol.converged
               else f"stopped after {sol.n_steps} steps without converging")
    raised = raise_effects(prep.lowered, fitted_spec)
    for b in biases.values():
        raised = _with_bias(raised, b)
    return FitResult(
        spec=raised, lowered_spec=fitted_spec,
        model=sol.state.model, state=sol.state, likelihood=likelihood,
        parameters=_raise_names(parameters, prep.lowered), correlation=_correlation(ident),
        free_names=[renames[n][0] if n in renames else n for n in sol.names], nll=nll,
        aic=2 * n_params + 2 * nll, bic=n_params * math.log(n_samples) + 2 * nll,
        n_params=n_params, n_samples=n_samples, rmse=metrics["rmse"],
        fit_percent=metrics["fit_percent"], per_run=metrics["per_run"],
        identifiability=_rename_identifiability(ident, {k: v[0] for k, v in renames.items()}),
        n_steps=sol.n_steps, converged=converged, message=message, dominant=dominant,
        n_evaluations=sol.n_evaluations, wall_time_s=time.perf_counter() - t_start, predictions=predictions,
        innovations=sol.innovations, theta=sol.theta, problem=sol.problem,
        lowered_as={target: (scale, power) for target, scale, power in renames.values()},
        biases=biases, method=sol.method or _DEFAULT_METHOD[likelihood])


_DEFAULT_METHOD = {
    "output_error": "forward sensitivities: the Jacobian formed, truncated Gauss-Newton "
                    "steps",
    "kalman": "Kalman likelihood: forward sensitivities of the filter, scoring steps",
}


def _bias_fits(prep: Prepared, sol: Solution, likelihood: str,
               ident: Identifiability) -> dict[str, BiasFit]:
    """Each bias column on the fitted model's free-run node temperatures and exact rates.

    Output error: at the jointly fitted τ's, each coefficient's std the marginal one,
    `σ² (XᵀX)⁻¹ + (∂ĉ/∂θ) Cov(θ) (∂ĉ/∂θ)ᵀ` (the block inverse of the joint linearized
    problem; None where it involves an undetermined direction). Kalman: the column is
    fitted after the filter, τ's by its own search, stds conditional on the thermal fit.
    """
    spec, data = prep.spec, prep.data
    if not spec.biases:
        return {}
    x, xdot = (np.asarray(a) for a in node_temperatures(sol.state.model, data,
                                                        sol.state.run_initial))
    mask = np.asarray(prep.bias.mask)
    strains = spec_strains(spec)
    taus = dict(zip([s.parameter for s in strains], np.exp(np.asarray(sol.state.bias_log_tau))))
    dc = None if likelihood == "kalman" or not len(sol.theta) else [
        np.asarray(d) for d in bias_coefficient_jacobian(sol.theta, sol.problem)]
    out = {}
    for j, b in enumerate(spec.biases):
        runs = [(e.ts, x[r, :e.n_times], np.where(mask[r, :e.n_times, j], e.biases[:, j], np.nan))
                for r, e in enumerate(prep.experiments)]
        rates = [xdot[r, :e.n_times] for r, e in enumerate(prep.experiments)]
        if likelihood == "kalman":
            out[b.column] = fit_bias(b, list(spec.effects), runs, spec.node_names, rates)
            continue
        # τ's held at the joint fit's values (their uncertainty is in Cov(θ))
        mine = iter(s for s in strains if s.column == b.column)
        held = [dataclasses.replace(e, parameters={**e.parameters, "time_constant": Parameter(
            float(taus[next(mine).parameter]), True)})
            if e.kind == "viscoelastic" and e.where[1] == b.column else e for e in spec.effects]
        fit = bias_fit_at(b, held, runs, spec.node_names, rates,
                          [taus[s.parameter] for s in strains if s.column == b.column])
        out[b.column] = fit if dc is None else _marginal_std(fit, dc[j], ident, sol.names)
    return out


def _marginal_std(fit: BiasFit, dc: np.ndarray, ident: Identifiability, names) -> BiasFit:
    """`fit` with the thermal parameters' uncertainty added to its coefficient stds;
    `dc` (free coefficients, free θ) is `∂ĉ/∂θ`, θ's elements named by `names`."""
    free = np.isfinite(fit.std)
    cov = np.asarray(ident.covariance)
    bad = np.array([n in ident.unidentifiable_parameters for n in names], bool)
    extra = np.einsum("ia,ab,ib->i", dc[:, ~bad], cov[np.ix_(~bad, ~bad)], dc[:, ~bad])
    undetermined = np.any(np.abs(dc[:, bad]) > 1e-12 * (1 + np.abs(dc).max()), axis=1)
    std = fit.std.copy()
    idx = np.flatnonzero(free)
    std[idx] = np.where(undetermined[:idx.size], np.nan,
                        np.sqrt(fit.std[idx] ** 2 + np.clip(extra[:idx.size], 0, None)))
    return dataclasses.replace(fit, std=std)


def _add_bias_metrics(metrics: dict, fit: BiasFit) -> None:
    """A bias column's RMSE and fit % (pooled and per run) into `fit_metrics`' dict."""
    measured = [p + r for p, r in zip(fit.predictions, fit.residuals)]  # NaN where missing
    c = fit.column
    metrics["rmse"][c] = rmse(np.concatenate(measured), np.concatenate(fit.predictions))
    metrics["fit_percent"][c] = fit_percent(np.concatenate(measured),
                                            np.concatenate(fit.predictions))
    for run, y, p in zip(metrics["per_run"], measured, fit.predictions):
        run["rmse"][c], run["fit_percent"][c] = rmse(y, p), fit_percent(y, p)


def _with_bias(spec: ModelSpec, fit: BiasFit) -> ModelSpec:
    """`spec` with one bias column's fitted coefficients, noise and viscoelastic τ and k."""
    biases, effects = list(spec.biases), list(spec.effects)
    for i, b in enumerate(biases):
        if b.column == fit.column:
            biases[i], effects = bias_to_spec(b, effects, fit)
    return spec.replace(biases=tuple(biases), effects=tuple(effects))


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
    for name in sol.at_bound:  # held at zero by the boundary check
        out[name] = {"value": 0.0, "std": None, "free": True, "at_bound": True}
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
