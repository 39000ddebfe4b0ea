"""Output error: weighted free-run residuals of every run, and their solve.

One simulator serves every use: the blocked exact-hold recurrence
(`dataset_block_outputs`), its outputs padded to whole blocks and the residuals zero
where nothing was measured. The default solver takes their Jacobian from forward
sensitivities (`output_sensitivity_parts`, equal to `jax.jacfwd` to roundoff);
optimistix solvers, the profile likelihood and the diagnosis use the same functions.
Estimated noise stds are held at their ML values inside the solve (the likelihood
profiled over them).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..compilation._traced_cache import stored_jit
from ..dynamics._sensitivity import (block_outputs_and_states, dataset_block_outputs,
                                     output_sensitivity_parts, pad_to_blocks)
from ._likelihood import ml_sigma, output_error_nll
from ._bias_residuals import bias_residuals, pushed_forward
from ._problem import (Prepared, Solution, _check_finite, _model_of, _perturbed_starts,
                       _prior, _Problem, _state, dataset, make_problem,
                       output_error_solution, template_at)
from ._side_by_side import side_by_side
from ._stationarity import escape, violations
from ._integration import fewest_substeps, integration_tolerance, shared_substeps, with_substeps
from ._solver import TruncatedGaussNewton, _flat_rows, _grams, gauss_newton, traced_settings
from ..model._parameters import free_parameters, with_free_parameters
from ..measurements._data import Experiment

if TYPE_CHECKING:
    from ._fit_result import FitResult


def _by_output(x):
    """(runs, times, outputs, ...) -> a tuple of (runs, times, ...), one per output."""
    return tuple(x[:, :, k] for k in range(x.shape[2]))


def _data_residuals(y, problem: _Problem):
    """Weighted sensor residuals (runs, blocks L, sensors) from sensor readings `y` padded
    to whole blocks (°C)."""
    data = problem.data
    p = data.outputs.shape[2]
    r = jnp.where(pad_to_blocks(data.mask), pad_to_blocks(data.outputs) - y, 0.0)
    return r / problem.sigma[None, None, :p]


def _split(y, problem: _Problem):
    """Simulated outputs (runs, blocks L, ...) -> `(sensor readings, node temperatures)`;
    the node temperatures are read out (and returned) only when the problem has bias
    columns, else None."""
    if problem.bias is None:
        return y, None
    p = problem.data.outputs.shape[2]
    return y[:, :, :p], y[:, :, p:]


def _bias_of(theta, problem: _Problem):
    """`(model, bias_log_tau)` at `theta`: what the bias columns' design needs."""
    s = _state(theta, problem)
    return s.model, s.bias_log_tau


def _bias_inputs(problem: _Problem):
    """`(inputs padded to whole blocks, run periods, bias stds)` for `_bias_residuals`."""
    data = problem.data
    return pad_to_blocks(data.inputs), data.dt, problem.sigma[data.outputs.shape[2]:]


def _oe_blocks(theta, problem: _Problem):
    """The residuals `(per_output, prior)`: `per_output` a tuple with each sensor's, then
    each bias column's, weighted data residuals (runs, blocks L), zero in the padding and
    where nothing was measured, so that `gauss_newton` returns each output's `JᵀJ`;
    `prior` (free,)."""
    return _oe_blocks_and_states(theta, problem)[0]


def _oe_blocks_and_states(theta, problem: _Problem):
    """`(_oe_blocks, states)`: a nonlinear model's simulated node temperatures (runs, T,
    n), which `_oe_blocks_jacobian` at the same `theta` reuses, else None."""
    model, run_initial = _model_of(theta, problem)
    y, states = block_outputs_and_states(model, problem.data, run_initial)
    y, x = _split(y, problem)
    r = _by_output(_data_residuals(y, problem))
    if x is not None:
        inputs, dt, sigma = _bias_inputs(problem)
        r = r + bias_residuals(*_bias_of(theta, problem), x, inputs, dt, problem.bias, sigma)
    return (r, _prior(theta, problem)), states


def _oe_flat(theta, problem: _Problem):
    """`_oe_blocks` as one vector (optimistix solvers): data rows in (runs, times,
    outputs) order without the padding, then the prior rows."""
    (r, prior), T = _oe_blocks(theta, problem), problem.data.outputs.shape[1]
    return jnp.concatenate([jnp.stack(r, axis=-1)[:, :T].reshape(-1), prior])


def _oe_blocks_jacobian(theta, problem: _Problem, states=None):
    """`(_oe_blocks(theta, problem), its Jacobian, the sensor predictions)` by forward
    sensitivities. The Jacobian has the residuals' structure, each output's leaf (runs,
    blocks L, free), the prior's (free, free); predictions (runs, times, sensors) °C.
    Bias columns take theirs from the node temperatures' sensitivities. `states`: from
    `_oe_blocks_and_states` at `theta`, when at hand."""
    data = problem.data
    p = data.outputs.shape[2]
    y_all, jacobian = output_sensitivity_parts(lambda t: _model_of(t, problem), theta, data,
                                               states)
    J_all = jacobian()
    y, x = _split(y_all, problem)
    J = jnp.where(pad_to_blocks(data.mask)[..., None],
                  -J_all[:, :, :p] / problem.sigma[None, None, :p, None], 0.0)
    r, J = _by_output(_data_residuals(y, problem)), _by_output(J)
    if x is not None:
        inputs, dt, sigma = _bias_inputs(problem)
        (rb, _), (Jb, _) = pushed_forward(lambda t: _bias_of(t, problem), theta, x,
                                          J_all[:, :, p:], inputs, dt, problem.bias, sigma)
        r, J = r + rb, J + Jb
    return ((r, _prior(theta, problem)), (J, jnp.diag(problem.prior_weight)),
            y[:, :data.outputs.shape[1]])


@stored_jit
def bias_coefficient_jacobian(theta, problem: _Problem):
    """Per bias column, `dĉ/dθ` (m_j, free) of its least-squares coefficients (the
    `_bias_residuals.design_matrices` columns) along the free parameters."""
    p = problem.data.outputs.shape[2]
    y_all, jacobian = output_sensitivity_parts(lambda t: _model_of(t, problem), theta,
                                               problem.data)
    inputs, dt, sigma = _bias_inputs(problem)
    _, (_, dc) = pushed_forward(lambda t: _bias_of(t, problem), theta, y_all[:, :, p:],
                                jacobian()[:, :, p:], inputs, dt, problem.bias, sigma)
    return dc


class _OEEvaluation(eqx.Module):
    """The output-error problem at one `theta`, for the fit's reports."""

    residuals: jax.Array  # weighted, data rows only, (runs, times, sensors + bias columns)
    gram: jax.Array  # JᵀJ of each column's weighted data rows, (columns, free, free)
    predictions: jax.Array  # (runs, times, sensors) °C
    num_evaluations: jax.Array | None = None  # residual evaluations at trial points
    jacobian: jax.Array | None = None  # of `residuals`, (runs, times, outputs, free)
    states: jax.Array | None = None  # a nonlinear model's node temperatures (runs, T, n)


@stored_jit
def _oe_evaluate(theta, problem: _Problem, full_jacobian: bool = False):
    """At `theta`: an `_OEEvaluation`; with `full_jacobian`, the weighted data residuals
    (runs, times, outputs) and their Jacobian (runs, times, outputs, free) instead."""
    T = problem.data.outputs.shape[1]
    if theta.shape[0] == 0:  # nothing free (a Kalman fit of the noise alone): no Jacobian
        model, run_initial = _model_of(theta, problem)
        y, _ = _split(dataset_block_outputs(model, problem.data, run_initial), problem)
        r = jnp.stack(_oe_blocks(theta, problem)[0], axis=-1)[:, :T]
        if full_jacobian:
            return r, jnp.zeros((*r.shape, 0))
        return _OEEvaluation(r, jnp.zeros((r.shape[2], 0, 0)), y[:, :T])
    (r, _), (J, _), y = _oe_blocks_jacobian(theta, problem)
    if full_jacobian:
        return jnp.stack(r, axis=-1)[:, :T], jnp.stack(J, axis=2)[:, :T]
    return _OEEvaluation(jnp.stack(r, axis=-1)[:, :T], jnp.stack(_grams(_flat_rows(J))), y)


def _solve_oe(theta0, problem: _Problem, solver, max_steps: int, estimated=None):
    """`(theta, steps, converged, _OEEvaluation at theta, stds)` from `gauss_newton` or an
    optimistix least-squares solver, in at most `max_steps` iterations.

    `estimated` (outputs,) bool: the outputs whose noise std is estimated. `gauss_newton`
    then maximises the likelihood profiled over them (`_ml_weights`) and `stds` are their
    ML values at `theta` (the others `problem.sigma`), the evaluation weighted by them;
    else `stds` is `problem.sigma`."""
    if estimated is None or not isinstance(solver, TruncatedGaussNewton):
        estimated = np.zeros(problem.sigma.shape[0], bool)
    return _solve_oe_jit(theta0, problem, *traced_settings(solver, max_steps),
                         jax.device_put(np.asarray(estimated, bool)))


def _ml_weights(r, problem: _Problem, estimated):
    """`gauss_newton`'s `reweight` for the output-error blocks `(per_output, prior)`: each
    estimated output's residuals scaled to its ML noise std at this point, `sqrt(N_k /
    Σ r_k²)` (N_k its measured samples; the std floored at 1e-12), the others and the
    prior rows unscaled."""
    per_output, _ = r
    counts = jnp.maximum(_measured_counts(problem), 1.0)
    floor = counts * (1e-12 / problem.sigma) ** 2
    w = tuple(jnp.where(estimated[k], jnp.sqrt(counts[k] / jnp.maximum(jnp.sum(x ** 2),
                                                                       floor[k])), 1.0)
              for k, x in enumerate(per_output))
    return w, jnp.ones((), r[1].dtype)


def _measured_counts(problem: _Problem):
    """Measured samples of each output (sensors, then bias columns), (outputs,)."""
    counts = jnp.sum(problem.data.mask, axis=(0, 1), dtype=problem.sigma.dtype)
    if problem.bias is None:
        return counts
    T = problem.data.outputs.shape[1]
    return jnp.concatenate([counts, jnp.sum(problem.bias.mask[:, :T], axis=(0, 1),
                                            dtype=problem.sigma.dtype)])


@stored_jit
def _solve_oe_jit(theta0, problem, solver, max_steps, estimated):
    if isinstance(solver, TruncatedGaussNewton):
        # A nonlinear model's Jacobian reuses the states of the accepted trial point (one
        # ETD2 scan fewer per step); a linear one keeps no states (and the hint's extra
        # residual evaluation would only add compile time).
        hinted = _model_of(theta0, problem)[0].is_nonlinear
        sol = gauss_newton(_oe_blocks_and_states if hinted else _oe_blocks, theta0, problem,
                           solver, jac=_oe_blocks_jacobian, max_steps=max_steps,
                           reweight=lambda r: _ml_weights(r, problem, estimated),
                           hinted=hinted)
        T = problem.data.outputs.shape[1]
        J = jnp.stack([j.reshape(*r.shape, -1) for j, r in zip(sol.jacobian[0],
                                                                sol.residuals[0])], axis=2)
        return sol.value, sol.num_steps, sol.converged, _OEEvaluation(
            jnp.stack(sol.residuals[0], axis=-1)[:, :T], jnp.stack(sol.grams[0]), sol.aux,
            sol.num_evaluations, J[:, :T], sol.hint), problem.sigma / jnp.stack(sol.weights[0])
    sol = optx.least_squares(_oe_flat, solver, theta0, problem, max_steps=max_steps,
                             throw=False)
    return (sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful,
            _oe_evaluate(sol.value, problem), problem.sigma)


def weighted_residuals_and_jacobian(theta, problem: _Problem, own_program: bool = False):
    """At `theta`: the weighted data residuals (runs, times, outputs), their Jacobian
    (runs, times, outputs, free) and a nonlinear model's node temperatures (runs, T, n;
    else None), as arrays. One Gauss-Newton evaluation without a step: an output-error
    fit's own compiled program serves (no other program to compile). `own_program`: a
    program of its own, compiled for this one evaluation (`_residuals_jacobian_states`),
    where the output-error solve was not compiled for the model (a Kalman fit's)."""
    if theta.shape[0] == 0:
        r, J = _oe_evaluate(theta, problem, full_jacobian=True)
        return np.asarray(r), np.asarray(J), None
    if own_program:
        r, J, states = _residuals_jacobian_states(theta, problem)
    else:
        evaluation = _solve_oe(theta, problem, TruncatedGaussNewton(), 1)[3]
        r, J, states = evaluation.residuals, evaluation.jacobian, evaluation.states
    return np.asarray(r), np.asarray(J), None if states is None else np.asarray(states)


@stored_jit(once=True)
def _residuals_jacobian_states(theta, problem: _Problem):
    """`weighted_residuals_and_jacobian`'s arrays from a program that evaluates them
    once, not the solve's: after a Kalman fit of a nonlinear model on PRBS1 the solve
    compiled in 2-3 s for this one evaluation (its scoring step's)."""
    states = _oe_blocks_and_states(theta, problem)[1]
    (r, _), (J, _), _ = _oe_blocks_jacobian(theta, problem, states)
    T = problem.data.outputs.shape[1]
    return jnp.stack(r, axis=-1)[:, :T], jnp.stack(J, axis=2)[:, :T], states


def _chi_square(theta, problem: _Problem) -> float:
    """χ² of the weighted data residuals at `theta` (prior rows excluded)."""
    return float(np.sum(weighted_residuals_and_jacobian(theta, problem)[0] ** 2))


@dataclass
class _Pass:
    """The last of a start's passes."""

    theta: jax.Array  # (free,)
    n_steps: int  # over all passes
    converged: bool
    sigma: np.ndarray  # (outputs,) °C, ML update of `used` where estimated
    used: np.ndarray  # (outputs,) °C, the weights of the last pass
    evaluation: _OEEvaluation  # at theta, weighted by `used`
    n_evaluations: int
    nll: float  # -log L at theta with the noise stds `sigma`


def _reweighted(start, prep: Prepared, theta0, solver, max_steps: int, say, outer: int = 4
                ) -> _Pass:
    """Solve from `start` with the estimated noise stds at their ML values: `gauss_newton`
    holds them there inside its solve (one pass, `_ml_weights`); an optimistix solver
    takes them as fixed weights, re-estimated between warm-started passes until they
    settle (up to `outer` passes)."""
    theta, total, evals = start, 0, 0
    sig, mask, estimated = prep.sigma, prep.mask(), ~prep.fixed_sigma
    for it in range(outer):
        problem = make_problem(prep.template, prep.index, prep.data, sig, theta0, bias=prep.bias)
        if theta.shape[0]:
            theta, steps, ok, sol, used = _solve_oe(theta, problem, solver, max_steps,
                                                    estimated)
        else:  # nothing physical to move (a Kalman fit of the noise alone)
            steps, ok, sol, used = 0, True, _oe_evaluate(theta, problem), sig
        used = np.asarray(used)
        total += int(steps)
        if sol.num_evaluations is not None:
            evals += int(sol.num_evaluations)
        new = np.where(estimated, np.maximum(ml_sigma(np.asarray(sol.residuals) * used, mask),
                                             1e-12), used)
        if estimated.any():
            say(f"output error pass {it + 1}: noise std {np.array2string(new, precision=4)}")
        settled = np.all(np.abs(np.log(new / used)) < 1e-3)
        sig = new
        if settled:
            break
    nll = output_error_nll(np.asarray(sol.residuals) * used, mask, sig)
    return _Pass(theta, total, bool(ok), sig, used, sol, evals, nll)


def fit_output_error(prep: Prepared, solver, max_steps: int, n_starts: int, seed: int,
                     say) -> Solution:
    """The output-error stage: the best of `n_starts` starts by likelihood (the first at
    the file's values, the others perturbed), each solved with `_reweighted`, side by
    side (`_side_by_side`; their progress lines are told in order when all finish)."""
    solver = solver or TruncatedGaussNewton()
    theta0 = free_parameters(prep.template, prep.index)
    best = None
    starts = [theta0] + _perturbed_starts(theta0, prep.names, n_starts - 1, seed)
    told = [[] for _ in starts] if len(starts) > 1 else [None]
    passes = side_by_side([functools.partial(_reweighted, start, prep, theta0, solver,
                                             max_steps, say if lines is None else lines.append)
                           for start, lines in zip(starts, told)])
    for i, (run, lines) in enumerate(zip(passes, told)):
        if lines is not None:
            for line in lines:
                say(line)
            say(f"start {i + 1}/{len(starts)}: -log L = {run.nll:.2f}")
        if best is None or (np.isfinite(run.nll) and run.nll < best.nll):
            best = run
    _check_finite(best.theta, theta0, prep.names)
    not_stationary = ""
    if isinstance(solver, TruncatedGaussNewton):
        best, not_stationary = _first_order(best, prep, theta0, solver, max_steps, say)
    if prep.template.model.is_nonlinear:
        best, prep = _accurate_at_solution(best, prep, theta0, solver, max_steps, say)
    # JᵀJ at theta from the last pass, re-weighted to the final stds.
    info = np.einsum("j,jab->ab", (best.used / best.sigma) ** 2,
                     np.asarray(best.evaluation.gram))
    return output_error_solution(
        prep, best.theta, theta0, best.sigma, info, best.nll, best.n_steps, best.converged,
        best.evaluation.predictions, best.n_evaluations,
        alternatives=[(np.asarray(r.theta), float(r.nll)) for r in passes if r is not best],
        not_stationary=not_stationary)


def _first_order(best: _Pass, prep: Prepared, theta0, solver: TruncatedGaussNewton,
                 max_steps: int, say) -> tuple[_Pass, str]:
    """`(best, why)`: `best` checked by the first-order conditions along the directions
    its solve left out (`_stationarity`); where they fail, walked out along them and
    solved again from there, the better kept. `why` words a direction that still fails
    ("" where none does): the fit is then not converged."""
    n_free = len(prep.names)

    def remaining(run: _Pass):
        return violations(np.asarray(run.evaluation.jacobian).reshape(-1, n_free),
                          np.asarray(run.evaluation.residuals).reshape(-1), prep.names,
                          solver.min_singular_value, solver.max_step)

    if n_free == 0 or best.evaluation.jacobian is None or not remaining(best):
        return best, ""
    problem = make_problem(prep.template, prep.index, prep.data, best.sigma, theta0,
                           bias=prep.bias)
    estimated, mask = ~prep.fixed_sigma, prep.mask()

    def at(theta):
        """−log L (noise stds at their ML values), weighted Jacobian and residuals: one
        evaluation of the solve's own program (one Jacobian, no step)."""
        _, _, _, evaluation, used = _solve_oe(jax.device_put(theta), problem, solver, 1,
                                              estimated)
        weighted = np.asarray(evaluation.residuals)
        r = weighted * np.asarray(used)
        sigma = np.where(estimated, np.maximum(ml_sigma(r, mask), 1e-12), np.asarray(used))
        return (output_error_nll(r, mask, sigma),
                np.asarray(evaluation.jacobian).reshape(-1, n_free), weighted.reshape(-1))

    theta, taken = escape(np.asarray(best.theta), at, prep.names, solver.min_singular_value,
                          solver.max_step, say)
    if taken:
        again = _reweighted(jax.device_put(theta), prep, theta0, solver, max_steps, say)
        if np.isfinite(again.nll) and again.nll < best.nll:
            say(f"after {taken} step(s) along it and a new solve: -log L {best.nll:.2f} -> "
                f"{again.nll:.2f}")
            best = dataclasses.replace(again, n_steps=best.n_steps + taken + again.n_steps,
                                       n_evaluations=best.n_evaluations + again.n_evaluations)
    found = remaining(best)
    return best, found[0].describe() if found else ""


def _accurate_at_solution(best: _Pass, prep: Prepared, theta0, solver, max_steps: int, say
                          ) -> tuple[_Pass, Prepared]:
    """`(best, prep)`, solved again with more ETD2 substeps from `best` as long as the
    solution needs more than it was solved with (`_integration`: the parameters moved to
    where the nonlinearity is stronger)."""
    p = len(prep.spec.sensors)
    while True:
        used = prep.template.model.etd2_substeps
        state = with_free_parameters(prep.template, prep.index, best.theta)
        substeps, error = fewest_substeps(state, prep.data, integration_tolerance(
            best.sigma[:p]), read_states=prep.bias is not None, at_least=used)
        substeps = shared_substeps(state.model, substeps)
        if substeps == used:
            say(f"nonlinear effects: {used} ETD2 step(s) per sample period, estimated "
                f"integration error {error:.2g} °C at the solution")
            return best, prep
        say(f"nonlinear effects: {used} ETD2 step(s) per sample period are not accurate "
            f"at the solution; solving again with {substeps}")
        prep = dataclasses.replace(prep, template=with_substeps(prep.template, substeps))
        again = _reweighted(best.theta, prep, theta0, solver, max_steps, say)
        best = dataclasses.replace(again, n_steps=best.n_steps + again.n_steps,
                                   n_evaluations=best.n_evaluations + again.n_evaluations)


def output_error_at(result: FitResult, experiments: list[Experiment]):
    """The output-error problem at a fit's values: `(data, weights, residuals, jacobian,
    states)`, `weights` (runs, T, p) = 1/σ where measured (σ the fitted noise stds, °C),
    `residuals` (N,) weighted and flattened, `jacobian` (N, P) in the fit's free
    physical parameters; `states`: a nonlinear model's node temperatures (runs, T, n),
    else None. `experiments` in the input order of `result.lowered_spec`."""
    data = dataset(experiments)
    template, index = template_at(result.lowered_spec, result.state.run_initial, data.n_runs)
    template = with_substeps(template, result.state.model.etd2_substeps)  # as the fit's
    theta = free_parameters(template, index)
    sigma = np.exp(np.asarray(template.model.log_noise))
    problem = make_problem(template, index, data, sigma, theta)
    weights = np.asarray(data.mask) / sigma[None, None, :]
    r, J, states = weighted_residuals_and_jacobian(theta, problem,
                                                   own_program=result.likelihood == "kalman")
    return data, weights, r.reshape(-1), J.reshape(-1, theta.shape[0]), states
