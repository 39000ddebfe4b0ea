"""Prediction-error fitting of a model to several runs: output error or Kalman likelihood.

`fit(spec, experiments, likelihood=...)` follows `optx.least_squares(fn, solver, y0, args)`:
the residual and loss functions are module-level and take everything through `args`,
so a second fit of the same structure (another unit, another candidate effect) reuses
the compilation. The default solvers are truncated: `TruncatedGaussNewton` (output
error) and `TruncatedNewton` (Kalman) leave the directions the data cannot determine
where they started and converge on the rest; any optimistix solver may be passed.

The optimizer sees one flat vector `theta`: logs of the positive physical
parameters and noise stds, and per-run initial temperatures in °C. With an
optimistix minimiser under the Kalman likelihood a weak Gaussian prior on `theta`
around the starting point (std `prior_log_std`, in log units: a factor e^3 ≈ 20 by
default) does that job instead: it keeps undetermined directions at their starting
values instead of letting them drift to 0 or infinity, changes well-determined
parameters by far less than their standard errors, and is left out of every
reported likelihood.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..measurements._data import Dataset, Experiment
from .._errors import InputError
from ._identifiability import Identifiability, identifiability
from ._likelihood import (kalman_nll, kalman_run, rts_smoother, output_error_residuals,
                          simulate_dataset)
from ..dynamics._sensitivity import dataset_block_outputs, output_sensitivity_parts, pad_to_blocks
from .._metrics import fit_metrics
from ..model._model import ThermalModel, model_to_spec
from ._newton import TruncatedNewton, newton
from ..model._parameters import FreeIndex, free_parameters, with_free_parameters
from ._solver import TruncatedGaussNewton, _flat_rows, _grams, gauss_newton
from ..model._spec import EFFECT_KINDS, ModelSpec
from ..model.effects import lower_effects, raise_effects

LIKELIHOODS = ("output_error", "kalman")


class FitState(eqx.Module):
    """Everything a fit moves: the model and each run's estimated initial temperatures."""

    model: ThermalModel
    run_initial: jax.Array  # (runs, len(model.initial_nodes)), °C


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
    predictions: list[np.ndarray] = field(repr=False, default_factory=list)
    # Kalman only: RTS-smoothed node temperatures per run, (times, nodes) mean and std (°C).
    smoothed: list[tuple[np.ndarray, np.ndarray]] = field(repr=False, default_factory=list)
    theta: np.ndarray | None = field(repr=False, default=None)
    problem: "_Problem | None" = field(repr=False, default=None)
    # Output error with the default solver: residual evaluations at trial points (each
    # of the `n_steps` iterations also evaluates residuals and Jacobian once).
    n_evaluations: int | None = None
    # Effect parameters fitted through a lowered entry: effect name -> (scale, power),
    # value = scale * lowered value ** power (e.g. a sensor lag's tau = C / G).
    lowered_as: dict[str, tuple[float, float]] = field(repr=False, default_factory=dict)


# ---------------------------------------------------------------------------
# The problem as pure functions of theta


class _Problem(eqx.Module):
    """What the residual and loss functions need besides theta (passed as optimistix `args`)."""

    template: FitState
    index: FreeIndex = eqx.field(static=True)
    data: Dataset
    sigma: jax.Array  # (outputs,) weights for output error (°C)
    prior_mean: jax.Array  # (free,)
    prior_weight: jax.Array  # (free,) 1/std of the prior; a huge weight pins a parameter


def _state(theta, problem: _Problem) -> FitState:
    return with_free_parameters(problem.template, problem.index, theta)


def _oe_residuals(theta, problem: _Problem):
    s = _state(theta, problem)
    r = output_error_residuals(s.model, problem.data, s.run_initial) / problem.sigma[None, None, :]
    prior = (theta - problem.prior_mean) * problem.prior_weight
    return r.reshape(-1), prior


def _kalman_loss(theta, problem: _Problem):
    s = _state(theta, problem)
    prior = (theta - problem.prior_mean) * problem.prior_weight
    return kalman_nll(s.model, problem.data, s.run_initial) + 0.5 * jnp.sum(prior ** 2)


def _oe_flat(theta, problem: _Problem):
    return jnp.concatenate(_oe_residuals(theta, problem))


def _model_of(theta, problem: _Problem):
    s = _state(theta, problem)
    return s.model, s.run_initial


def _oe_blocks(theta, problem: _Problem):
    """The residuals the solver sees: `(per_output, prior)`, `per_output` a tuple with the
    weighted data residuals of each output (runs, blocks L) padded to whole blocks of
    `_sensitivity` and zero where nothing was measured (`_oe_flat`'s values, reordered,
    with the padding as extra zeros), so that the solver returns each output's `JᵀJ`.
    One discretization per run with a fast-compiling matrix exponential."""
    model, run_initial = _model_of(theta, problem)
    y = dataset_block_outputs(model, problem.data, run_initial)
    return _by_output(_data_residuals(y, problem)), _prior(theta, problem)


def _by_output(x):
    """(runs, times, outputs, ...) -> a tuple of (runs, times, ...), one per output."""
    return tuple(x[:, :, k] for k in range(x.shape[2]))


def _data_residuals(y, problem: _Problem):
    """Weighted data residuals from predictions `y` padded to whole blocks."""
    data = problem.data
    r = jnp.where(pad_to_blocks(data.mask), pad_to_blocks(data.outputs) - y, 0.0)
    return r / problem.sigma[None, None, :]


def _prior(theta, problem: _Problem):
    return (theta - problem.prior_mean) * problem.prior_weight


def _oe_blocks_jacobian(theta, problem: _Problem):
    """`(_oe_blocks(theta, problem), its Jacobian, the predictions)` by forward
    sensitivities (`_sensitivity.output_sensitivity_parts`): equal to
    `jax.jacfwd(_oe_flat)` to roundoff, at a fraction of its cost. The Jacobian has the
    residuals' structure, each output's leaf (runs, blocks L, params), the prior's
    (params, params); the predictions are the free-run outputs (runs, times, outputs)."""
    data = problem.data
    y, jacobian = output_sensitivity_parts(lambda t: _model_of(t, problem), theta, data)
    J = jnp.where(pad_to_blocks(data.mask)[..., None],
                  -jacobian() / problem.sigma[None, None, :, None], 0.0)
    return ((_by_output(_data_residuals(y, problem)), _prior(theta, problem)),
            (_by_output(J), jnp.diag(problem.prior_weight)), y[:, :data.outputs.shape[1]])


def _solve_oe(theta0, problem, solver, max_steps):
    """`(theta, steps, converged, _OEEvaluation at theta)` from `gauss_newton` or an
    optimistix least-squares solver.

    A `TruncatedGaussNewton`'s settings are passed as arrays, so that fits with other
    tolerances or dampings (warm-started passes) reuse one compilation.
    """
    if isinstance(solver, TruncatedGaussNewton):
        solver = jax.tree.map(lambda x: jax.device_put(np.asarray(x, float)), solver)
    return _solve_oe_jit(theta0, problem, solver, max_steps)


class _OEEvaluation(eqx.Module):
    """What the fit reports need at the solution."""

    residuals: jax.Array  # weighted, data rows only, (runs, times, outputs)
    gram: jax.Array  # JᵀJ of each output's weighted data rows, (outputs, params, params)
    predictions: jax.Array  # (runs, times, outputs)
    num_evaluations: jax.Array | None = None  # residual evaluations at trial points


@eqx.filter_jit
def _solve_oe_jit(theta0, problem, solver, max_steps):
    if isinstance(solver, TruncatedGaussNewton):
        sol = gauss_newton(_oe_blocks, theta0, problem, solver, jac=_oe_blocks_jacobian)
        T = problem.data.outputs.shape[1]
        return sol.value, sol.num_steps, sol.converged, _OEEvaluation(
            jnp.stack(sol.residuals[0], axis=-1)[:, :T], jnp.stack(sol.grams[0]), sol.aux,
            sol.num_evaluations)
    sol = optx.least_squares(_oe_residuals, solver, theta0, problem, max_steps=max_steps,
                             throw=False)
    return (sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful,
            _oe_evaluate(sol.value, problem))


@eqx.filter_jit
def _solve_kalman(theta0, problem, solver, max_steps):
    """(theta, steps, converged) from `newton` or an optimistix minimiser."""
    if isinstance(solver, TruncatedNewton):
        sol = newton(_kalman_loss, theta0, problem, solver)
        return sol.value, sol.num_steps, sol.converged
    sol = optx.minimise(_kalman_loss, solver, theta0, problem, max_steps=max_steps, throw=False)
    return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


@eqx.filter_jit
def _kalman_hessian(theta, problem):
    return jax.hessian(lambda t: _kalman_loss(t, problem))(theta)


@eqx.filter_jit
def _kalman_nll_only(theta, problem):
    s = _state(theta, problem)
    return kalman_nll(s.model, problem.data, s.run_initial)


# Compiled once per structure: called eagerly, `simulate_dataset` would trace (and its
# scans compile) anew on every fit.
_simulate_jit = eqx.filter_jit(simulate_dataset)


@eqx.filter_jit
def _oe_raw(theta, problem):
    s = _state(theta, problem)
    return output_error_residuals(s.model, problem.data, s.run_initial)


# ---------------------------------------------------------------------------
# Names and masks


def _masks(spec: ModelSpec, model: ThermalModel, n_runs: int, likelihood: str):
    """Boolean masks shaped like `FitState` (True = free) and the dotted name of every element."""
    kalman = likelihood == "kalman"
    nodes = spec.node_names
    net_masks = [
        ([not n.capacitance.fixed for n in spec.nodes],
         [f"nodes.{n.name}.capacitance" for n in spec.nodes]),
        ([not k.conductance.fixed for k in spec.links],
         [f"links.{k.key}.conductance" for k in spec.links]),
        ([not b.conductance.fixed for b in spec.boundaries],
         [f"boundaries.{b.key}.conductance" for b in spec.boundaries]),
        ([not h.gain.fixed for h in spec.heat_inputs],
         [f"heat_inputs.{h.key}.gain" for h in spec.heat_inputs]),
        ([kalman and not (s.noise is not None and s.noise.fixed) for s in spec.sensors],
         [f"sensors.{s.column}.noise" for s in spec.sensors]),
        ([kalman and not (n.process_noise is not None and n.process_noise.fixed)
          for n in spec.nodes], [f"nodes.{n.name}.process_noise" for n in spec.nodes]),
        ([False] * len(nodes), [f"nodes.{n}.initial" for n in nodes]),
        ([False] * len(nodes), [f"nodes.{n}.initial_std" for n in nodes]),
    ]
    effects = {(e.kind, e.where): e for e in spec.effects}
    net_masks.append((
        [not (p in effects[(t.kind, t.where)].parameters
              and effects[(t.kind, t.where)].parameters[p].fixed)
         for t in model.effect_terms for p in t.parameters],
        [f"effects.{t.kind}.{'-'.join(t.where)}.{p}" for t in model.effect_terms
         for p in t.parameters]))
    init_free = [not spec.nodes[i].initial.fixed for i in model.initial_nodes]
    run_mask = np.array([init_free] * n_runs, dtype=bool).reshape(n_runs, len(init_free))
    run_names = [[f"runs.{r}.nodes.{nodes[i]}.initial" for i in model.initial_nodes]
                 for r in range(n_runs)]
    arrays = [np.array(m, dtype=bool) for m, _ in net_masks]
    template_mask = FitState(
        ThermalModel(
            eqx.tree_at(lambda n: (n.log_capacitance, n.log_conductance,
                                   n.log_boundary_conductance, n.log_heat_gain),
                        model.network, tuple(arrays[:4])),
            arrays[4], arrays[5], arrays[6], arrays[7], model.initial_nodes, arrays[8],
            model.effect_terms),
        run_mask)
    names = [nm for _, nms in net_masks for nm in nms] + [nm for row in run_names for nm in row]
    flat_mask = np.concatenate([*arrays, run_mask.reshape(-1)])
    free_names = [nm for nm, f in zip(names, flat_mask) if f]
    return template_mask, free_names


def _reorder_inputs(experiments, columns, order):
    """Experiments with their input columns rearranged from `columns` to `order` (a
    lowered spec lists the same columns, maybe in another order)."""
    if tuple(columns) == tuple(order):
        return experiments
    idx = [list(columns).index(c) for c in order]
    return [dataclasses.replace(e, inputs=e.inputs[:, idx]) for e in experiments]


def _raise_names(parameters: dict, lowered) -> dict:
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


def _is_log(name: str) -> bool:
    """Whether the optimizer moves this parameter's log (positive parameters)."""
    if name.startswith("effects."):
        parts = name.split(".")
        return parts[-1] in EFFECT_KINDS[parts[1]].positive
    return not name.endswith(".initial")


# ---------------------------------------------------------------------------


def fit(spec: ModelSpec, experiments: list[Experiment], *, likelihood: str = "output_error",
        solver=None, max_steps: int = 200, prior_log_std: float = 3.0, n_starts: int = 1,
        seed: int = 0, progress=None, holdout: int | None = None) -> FitResult:
    """Fit the free parameters of `spec` to several runs at once.

    **Arguments:**

    - `spec`: the model (its fixed/free flags say what is estimated).
    - `experiments`: one `Experiment` per run; parameters are shared, each run
      has its own initial state.
    - `likelihood`: `"output_error"` (truncated Gauss-Newton on free-run residuals
      weighted by each sensor's noise; estimated noise stds take their ML
      values, iterated to convergence) or `"kalman"` (truncated Newton with exact
      Hessians on the Kalman prediction-error likelihood, started from the
      output-error fit).
    - `solver`: default `TruncatedGaussNewton()` for output error and
      `TruncatedNewton()` for Kalman; an optimistix least-squares solver (output
      error) or minimiser (Kalman) may be passed instead.
    - `prior_log_std`: std (log units) of the weak prior that keeps unidentifiable
      directions at their starting values when an optimistix minimiser fits the
      Kalman likelihood (the truncated solvers need none).
    - `n_starts`: more than 1 adds starts perturbed by a log-normal factor
      (std 0.5); the best likelihood wins.
    - `progress`: optional callable taking a one-line string.
    - `holdout`: index of a run left out of the likelihood (its measurements are masked;
      it is still simulated, so `predictions` hold its out-of-sample prediction).

    **Returns:** a `FitResult`.
    """
    if likelihood not in LIKELIHOODS:
        raise InputError(f"unknown likelihood '{likelihood}'; use one of {list(LIKELIHOODS)}.",
                         field="--likelihood")
    t_start = time.perf_counter()
    say = progress or (lambda _msg: None)
    original, lowered = spec, lower_effects(spec)
    spec = lowered.spec
    experiments = _reorder_inputs(experiments, original.input_columns, spec.input_columns)
    _check_runs(spec, experiments)
    data = Dataset.from_experiments(experiments)
    data = dataclasses.replace(data, names=())  # names are for reports: no recompilation
    if holdout is not None:
        data = dataclasses.replace(data, mask=data.mask.at[holdout].set(False))
    model = ThermalModel.from_spec(spec)
    k = len(model.initial_nodes)
    initial = np.asarray(model.initial)[np.array(model.initial_nodes, dtype=int)]
    run_initial = np.broadcast_to(initial, (data.n_runs, k))
    template = FitState(model, jax.device_put(np.array(run_initial)))

    oe_mask, oe_names = _masks(spec, model, data.n_runs, "output_error")
    if not oe_names and likelihood == "output_error":
        raise InputError("nothing to fit: every parameter is fixed. Make at least one "
                         "capacitance, conductance or gain a bare number.", file=spec.source)
    fixed_sigma = np.array([s.noise is not None and s.noise.fixed for s in spec.sensors])
    sigma = np.exp(np.asarray(model.log_noise))

    # -- output error, with the estimated noise stds iterated to their ML values
    index = FreeIndex(oe_mask)
    theta0 = _free_parameters_np(template, index)
    starts = [theta0] + _perturbed_starts(theta0, oe_names, n_starts - 1, seed)
    best = None
    mask = np.asarray(data.mask)
    for s_i, start in enumerate(starts):
        theta, n_steps, ok, sig, sol, used, evals = _fit_output_error(
            start, theta0, template, index, data, sigma, fixed_sigma,
            solver if likelihood == "output_error" else None, max_steps, prior_log_std, say)
        res = np.asarray(sol.residuals) * used
        nll = _np_output_error_nll(res, mask, sig)
        if n_starts > 1:
            say(f"start {s_i + 1}/{len(starts)}: -log L = {nll:.2f}")
        if best is None or (np.isfinite(nll) and nll < best[4]):
            best = (theta, n_steps, ok, sig, nll, sol, used, evals)
    theta, n_steps, converged, sigma, nll, oe_solution, sigma_used, n_evals = best
    _check_finite(theta, theta0, oe_names)
    state = _with_free_parameters_np(template, index, theta)
    state = FitState(eqx.tree_at(lambda m: m.log_noise, state.model, jax.device_put(np.log(sigma))),
                     state.run_initial)

    if likelihood == "output_error":
        problem = _Problem(template, index, data, jax.device_put(sigma), theta0,
                           jax.device_put(np.zeros(theta0.shape)))
        # JᵀJ at theta from the last pass, re-weighted to the final stds.
        info = np.einsum("j,jab->ab", (sigma_used / sigma) ** 2, np.asarray(oe_solution.gram))
        free_names = oe_names
        # Estimated noise stds are parameters too (ML: std(σ) = σ / sqrt(2 N)).
        n_meas = np.asarray(data.mask).sum(axis=(0, 1))
        noise_params = {f"sensors.{c}.noise": (float(sigma[j]),
                                                float(sigma[j] / np.sqrt(2 * max(n_meas[j], 1))))
                        for j, c in enumerate(spec.sensor_columns) if not fixed_sigma[j]}
    else:
        k_mask, k_names = _masks(spec, model, data.n_runs, "kalman")
        k_index = FreeIndex(k_mask)
        k_template = state  # warm start from the output-error fit
        th0 = free_parameters(k_template, k_index)
        prior_mean = free_parameters(template, k_index)
        k_solver = solver or TruncatedNewton()
        weight = 0.0 if isinstance(k_solver, TruncatedNewton) else 1.0 / prior_log_std
        problem = _Problem(k_template, k_index, data, jnp.asarray(sigma), prior_mean,
                           jnp.full_like(th0, weight))
        say(f"Kalman likelihood: {len(k_names)} parameters, started from the output-error fit")
        theta, n_steps, converged = _solve_kalman(th0, problem, k_solver, max_steps)
        _check_finite(theta, th0, k_names)
        n_steps, converged = int(n_steps), bool(converged)
        state = _state(theta, problem)
        problem_np = _Problem(k_template, k_index, data, jnp.asarray(sigma), prior_mean,
                              jnp.zeros_like(th0))
        info = np.asarray(_kalman_hessian(theta, problem_np))
        nll = float(_kalman_nll_only(theta, problem_np))
        free_names = k_names
        noise_params = {}
        problem = problem_np
    fitted_spec = model_to_spec(state.model, spec, process_noise=likelihood == "kalman")
    ident = identifiability(info, free_names, fitted_spec,
                            sample_period=float(np.max(np.asarray(data.dt))))
    values = np.asarray(theta)
    cov = ident.covariance
    stds_theta = np.sqrt(np.clip(np.diag(cov), 0, None))
    parameters: dict[str, dict] = {}
    for j, nm in enumerate(free_names):
        v = float(np.exp(values[j])) if _is_log(nm) else float(values[j])
        sd = None
        if nm not in ident.unidentifiable_parameters and np.isfinite(stds_theta[j]):
            sd = float(v * stds_theta[j]) if _is_log(nm) else float(stds_theta[j])
        parameters[nm] = {"value": v, "std": sd, "free": True}
    for nm, (v, sd) in noise_params.items():
        parameters[nm] = {"value": v, "std": sd, "free": True}
    _add_fixed_parameters(parameters, spec)
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / d[:, None] / d[None, :]

    if likelihood == "output_error":
        preds = np.asarray(oe_solution.predictions)
    else:
        preds = np.asarray(_simulate_jit(state.model, data, state.run_initial))
    preds_list = [preds[r, :n] for r, n in enumerate(data.lengths)]
    n_params = len(free_names) + len(noise_params)
    n_samples = int(np.asarray(data.mask).sum())
    metrics = fit_metrics(spec.sensor_columns, experiments, preds_list)
    smoothed = []
    if likelihood == "kalman":
        m_s, s_s = _smooth(state.model, data, state.run_initial)
        smoothed = [(np.asarray(m_s[r, :n]), np.asarray(s_s[r, :n]))
                    for r, n in enumerate(data.lengths)]
    message = "converged" if converged else f"stopped after {n_steps} steps without converging"
    say(f"fit done: -log L = {nll:.2f}, {n_params} parameters, {message}")
    parameters = _raise_names(parameters, lowered)
    renames = lowered.renames()
    free_names = [renames[n][0] if n in renames else n for n in free_names]
    ident = _rename_identifiability(ident, {k: v[0] for k, v in renames.items()})
    return FitResult(
        spec=raise_effects(lowered, fitted_spec), lowered_spec=fitted_spec, model=state.model, state=state, likelihood=likelihood,
        parameters=parameters, correlation=corr, free_names=free_names, nll=nll,
        aic=2 * n_params + 2 * nll, bic=n_params * math.log(n_samples) + 2 * nll,
        n_params=n_params, n_samples=n_samples, rmse=metrics["rmse"],
        fit_percent=metrics["fit_percent"], per_run=metrics["per_run"], identifiability=ident,
        n_steps=n_steps, converged=converged, message=message,
        n_evaluations=n_evals if likelihood == "output_error" else None,
        wall_time_s=time.perf_counter() - t_start, predictions=preds_list, smoothed=smoothed,
        theta=np.asarray(theta), problem=problem,
        lowered_as={target: (scale, power) for target, scale, power in renames.values()})


@eqx.filter_jit
def _smooth(model, data: Dataset, run_initial):
    def one(ts, u, y, mask, r0):
        kf = kalman_run(model, ts, u, y, mask, r0)
        return rts_smoother(model, ts, kf)

    return jax.vmap(one)(data.ts, data.inputs, data.outputs, data.mask, run_initial)


def profile_interval(result: FitResult, name: str, level: float = 0.95, max_refits: int = 24
                     ) -> tuple[float | None, float | None]:
    """Profile-likelihood confidence interval of one free parameter (output error).

    The parameter is pinned at trial values (a stiff prior row in the same
    compiled problem) while every other free parameter is refitted; the
    interval's ends are where `2 (nll_pinned - nll_min)` reaches the
    chi-square(1) quantile of `level`, found by bracketing and bisection.
    Noise stds stay at their fitted values. An end that never reaches the
    threshold (an unidentifiable side) is None. An effect parameter fitted through
    a lowered entry (a sensor lag's `tau` as the conductance `C / tau`) is profiled
    in that entry and its ends mapped back.
    """
    from scipy.stats import chi2

    if result.likelihood != "output_error" or result.problem is None:
        raise InputError("profile intervals are available for output-error fits; refit with "
                         "likelihood='output_error'.", field="--profile")
    if name not in result.free_names:
        raise InputError(f"'{name}' is not a free parameter; free ones are {result.free_names}.",
                         field="--profile")
    j = result.free_names.index(name)
    problem, theta_hat = result.problem, jnp.asarray(result.theta)
    threshold = float(chi2.ppf(level, 1))
    base = 2 * float(gauss_newton_cost(theta_hat, problem))
    pin = jnp.zeros_like(theta_hat).at[j].set(1e7)

    def excess(value: float) -> float:
        pinned = _Problem(problem.template, problem.index, problem.data, problem.sigma,
                          theta_hat.at[j].set(value), pin)
        theta = _solve_oe(theta_hat.at[j].set(value), pinned, TruncatedGaussNewton(), 100)[0]
        chi = 2 * float(gauss_newton_cost(theta, problem))
        return chi - base - threshold

    std = result.parameters[name]["std"]
    value = float(theta_hat[j])
    log = _is_log(name)
    step = (std / result.parameters[name]["value"] if log else std) if std else 0.5
    ends = []
    for sign in (-1.0, 1.0):
        lo, hi, width, refits = value, None, 1.96 * step, 0
        while refits < max_refits:
            trial = value + sign * width
            refits += 1
            if excess(trial) > 0:
                hi = trial
                break
            lo, width = trial, width * 2
        if hi is None:
            ends.append(None)
            continue
        for _ in range(max(0, max_refits - refits)):
            mid = 0.5 * (lo + hi)
            if abs(hi - lo) < 1e-3 * 1.96 * step:  # relative to the expected half-width
                break
            if excess(mid) > 0:
                hi = mid
            else:
                lo = mid
        end = 0.5 * (lo + hi)
        ends.append(float(np.exp(end)) if log else end)
    if name in result.lowered_as:  # value = scale * lowered ** power, monotone
        scale, power = result.lowered_as[name]
        ends = [None if e is None else scale * e ** power for e in ends]
        if power < 0:
            ends = ends[::-1]
    return ends[0], ends[1]


@eqx.filter_jit
def gauss_newton_cost(theta, problem):
    """½χ² of the weighted output-error residuals (prior rows excluded)."""
    r, _ = _oe_residuals(theta, problem)
    return 0.5 * jnp.sum(r ** 2)


# Damping of the first step of a warm-started pass (relative to the largest squared
# singular value): the start is the previous pass's optimum, moved only by re-weighting.
_WARM_DAMPING = 1e-9


def _fit_output_error(start, theta0, template, index, data, sigma, fixed_sigma, solver,
                      max_steps, prior_log_std, say, outer=4):
    """Truncated Gauss-Newton on weighted residuals, re-weighting estimated stds to their
    ML values until they settle (a few outer passes, each warm-started from the last and
    reusing the compilation).

    Returns `(theta, steps, converged, sigma, evaluation, sigma_used, evaluations)`: `evaluation` (an
    `_OEEvaluation`) holds the residuals, Jacobian and predictions at `theta`, weighted by
    `sigma_used`, the stds of the last pass (`sigma` are their ML update)."""
    solver = solver or TruncatedGaussNewton()
    theta, total, ok, evals = start, 0, False, 0
    sig = np.asarray(sigma, float)
    mask = np.asarray(data.mask)
    for it in range(outer):
        problem = _Problem(template, index, data, jax.device_put(sig), theta0,
                           jax.device_put(np.zeros(theta0.shape)))
        if theta.shape[0]:
            theta, steps, ok, *evaluation = _solve_oe(theta, problem, solver, max_steps)
        else:  # nothing physical to move (a Kalman fit of the noise alone)
            steps, ok, evaluation = 0, True, []
        sol = evaluation[0] if evaluation else _oe_evaluate(theta, problem)
        total += int(steps)
        if sol.num_evaluations is not None:
            evals += int(sol.num_evaluations)
        ok = bool(ok)
        used = sig
        if fixed_sigma.all():
            break
        res = np.asarray(sol.residuals) * sig
        n = np.maximum(mask.sum(axis=(0, 1)), 1)
        new = np.where(fixed_sigma, sig, np.maximum(np.sqrt((res ** 2).sum(axis=(0, 1)) / n),
                                                    1e-12))
        say(f"output error pass {it + 1}: noise std {np.array2string(new, precision=4)}")
        if np.all(np.abs(np.log(new / sig)) < 1e-3):
            sig = new
            break
        sig = new
        if isinstance(solver, TruncatedGaussNewton):
            solver = eqx.tree_at(lambda t: t.initial_damping, solver,
                                 min(float(solver.initial_damping), _WARM_DAMPING))
    return theta, total, ok, sig, sol, used, evals


@eqx.filter_jit
def _oe_evaluate(theta, problem) -> _OEEvaluation:
    """Weighted data residuals (runs, times, outputs), the Gram matrix of each output and
    the predictions at `theta`."""
    T, p = problem.data.outputs.shape[1:]
    if theta.shape[0] == 0:  # nothing free (a Kalman fit of the noise alone): no Jacobian
        model, run_initial = _model_of(theta, problem)
        y = dataset_block_outputs(model, problem.data, run_initial)
        return _OEEvaluation(_data_residuals(y, problem)[:, :T], jnp.zeros((p, 0, 0)), y[:, :T])
    (r, _), (J, _), y = _oe_blocks_jacobian(theta, problem)
    return _OEEvaluation(jnp.stack(r, axis=-1)[:, :T], jnp.stack(_grams(_flat_rows(J))), y)


def _np_output_error_nll(residuals, mask, sigma) -> float:
    """`output_error_nll` in NumPy (no compilation)."""
    n = mask.sum(axis=(0, 1))
    ssr = (residuals ** 2).sum(axis=(0, 1))
    return float(np.sum(0.5 * n * (np.log(2 * np.pi) + 2 * np.log(sigma)) + 0.5 * ssr / sigma ** 2))


def _perturbed_starts(theta0, names, n, seed):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(max(n, 0)):
        step = np.array([rng.normal(0, 0.5) if _is_log(nm) else rng.normal(0, 1.0)
                         for nm in names])
        out.append(theta0 + jnp.asarray(step))
    return out


def _check_finite(theta, theta0, names):
    theta = np.asarray(theta)
    if np.all(np.isfinite(theta)):
        return
    bad = [nm for nm, t in zip(names, theta) if not np.isfinite(t)]
    jump = np.abs(np.nan_to_num(theta - np.asarray(theta0), nan=np.inf))
    worst = names[int(np.argmax(jump))] if len(names) else "?"
    raise InputError(f"the fit diverged: {', '.join(bad) or worst} ran away to a non-finite "
                     f"value (largest move: {worst}). Check that parameter's starting value and "
                     "units, fix it from design data, or give the data more excitation.")


def _slowest_time_constant(spec: ModelSpec) -> float:
    """`max(ThermalNetwork.from_spec(spec).time_constants())` in NumPy (s; inf when a node
    has no path to a boundary): eager JAX would compile a dozen small programs per fit."""
    idx = {n: i for i, n in enumerate(spec.node_names)}
    c = np.array([n.capacitance.value for n in spec.nodes], float)
    K = np.zeros((len(c), len(c)))
    for link in spec.links:
        i, j = (idx[x] for x in link.between)
        g = link.conductance.value
        K[i, i] += g
        K[j, j] += g
        K[i, j] -= g
        K[j, i] -= g
    for b in spec.boundaries:
        K[idx[b.node], idx[b.node]] += b.conductance.value
    sq = np.sqrt(c)
    S = K / sq[:, None] / sq[None, :]
    with np.errstate(divide="ignore"):
        return float(np.max(1.0 / np.linalg.eigvalsh(0.5 * (S + S.T))))


def _free_parameters_np(tree, index: FreeIndex) -> jax.Array:
    """`free_parameters(tree, index)` by NumPy indexing (no eager JAX compilations)."""
    leaves = jax.tree.leaves(eqx.filter(tree, eqx.is_array))
    parts = [np.ravel(np.asarray(leaf))[np.array(ix, dtype=int)]
             for leaf, ix in zip(leaves, index.per_leaf)]
    return jax.device_put(np.concatenate(parts) if parts else np.zeros((0,)))


def _with_free_parameters_np(tree, index: FreeIndex, theta):
    """`with_free_parameters(tree, index, theta)` by NumPy indexing."""
    dynamic, static = eqx.partition(tree, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    theta = np.asarray(theta)
    out, offset = [], 0
    for leaf, ix in zip(leaves, index.per_leaf):
        a = np.array(leaf)
        if ix:
            flat = a.reshape(-1)
            flat[np.array(ix, dtype=int)] = theta[offset:offset + len(ix)]
            a = flat.reshape(a.shape)
        out.append(jax.device_put(a))
        offset += len(ix)
    return eqx.combine(jax.tree.unflatten(treedef, out), static)


def _check_runs(spec: ModelSpec, experiments: list[Experiment]) -> None:
    if not experiments:
        raise InputError("no runs given; pass at least one --data file.", field="--data")
    slowest = _slowest_time_constant(spec)
    for e in experiments:
        measured = np.isfinite(e.outputs)
        if not measured.any():
            raise InputError("no sensor data in this run: every sensor cell is empty or NaN.",
                             file=e.name, field=",".join(spec.sensor_columns))
        for j in np.flatnonzero(~measured.any(axis=0)):
            col = spec.sensor_columns[j] if j < len(spec.sensor_columns) else f"output {j}"
            raise InputError(f"sensor column {col!r} has no readings in this run (every cell is "
                             "empty or nan); drop it from the model or use a run that measured "
                             "it.", file=e.name, field=col)
        if e.ts[-1] - e.ts[0] < slowest:
            warnings.warn(f"{e.name}: the run lasts {e.ts[-1] - e.ts[0]:.0f} s, shorter than the "
                          f"slowest time constant of the starting model ({slowest:.0f} s); the "
                          "slow parameters will be poorly determined.", stacklevel=3)


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


# ---------------------------------------------------------------------------
# Evaluations of a fitted model, for diagnosis


def output_error_at(result: FitResult, experiments: list[Experiment]):
    """The output-error problem at a fit's values: `(data, weights, residuals, jacobian)`,
    `weights` (runs, T, p) = 1/σ where measured (σ the fitted noise stds), `residuals`
    (N,) weighted and flattened, `jacobian` (N, P) in the fit's free physical parameters.
    `experiments` in the input order of `result.lowered_spec`."""
    spec = result.lowered_spec
    data = Dataset.from_experiments(experiments)
    data = dataclasses.replace(data, names=())
    model = ThermalModel.from_spec(spec)
    template = FitState(model, jnp.asarray(result.state.run_initial))
    mask, _ = _masks(spec, model, data.n_runs, "output_error")
    index = FreeIndex(mask)
    theta = _free_parameters_np(template, index)
    sigma = np.exp(np.asarray(model.log_noise))
    problem = _Problem(template, index, data, jax.device_put(sigma), theta,
                       jax.device_put(np.zeros(theta.shape)))
    weights = np.asarray(data.mask) / sigma[None, None, :]
    r, J = _oe_samples_jacobian(theta, problem)
    return data, weights, np.asarray(r).reshape(-1), np.asarray(J).reshape(-1, theta.shape[0])


@eqx.filter_jit
def _oe_samples_jacobian(theta, problem):
    """Weighted data residuals (runs, T, p) and their Jacobian (runs, T, p, P)."""
    T = problem.data.outputs.shape[1]
    if theta.shape[0] == 0:
        return _oe_evaluate(theta, problem).residuals, jnp.zeros((*problem.data.outputs.shape, 0))
    (r, _), (J, _), _ = _oe_blocks_jacobian(theta, problem)
    return jnp.stack(r, axis=-1)[:, :T], jnp.stack(J, axis=2)[:, :T]


@eqx.filter_jit
def _innovations(model, data: Dataset, run_initial):
    def one(ts, u, y, mask, r0):
        kf = kalman_run(model, ts, u, y, mask, r0)
        return kf.innovations / jnp.where(mask, kf.innovation_std, 1.0)

    return jax.vmap(one)(data.ts, data.inputs, data.outputs, data.mask, run_initial)


def standardized_innovations(result: FitResult) -> list[np.ndarray]:
    """Kalman fits: each run's one-step innovations over their std, (T, p), NaN where
    nothing was measured."""
    data = result.problem.data
    e = np.asarray(_innovations(result.model, data, result.state.run_initial))
    mask = np.asarray(data.mask)
    return [np.where(mask[r, :len(p)], e[r, :len(p)], np.nan)
            for r, p in enumerate(result.predictions)]
