"""The Kalman stage of a fit: the prediction-error likelihood, started from output error.

The default `TruncatedNewton` leaves undetermined directions where they start; an
optimistix minimiser gets a weak Gaussian prior on `theta` around the file's values
instead (std `prior_log_std` in log units), left out of every reported likelihood.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._likelihood import kalman_nll, kalman_runs, rts_smoother, simulate_dataset
from ._newton import TruncatedNewton, newton
from ._solver import traced_settings
from ._problem import Prepared, Solution, _check_finite, _prior, _state, make_problem
from ..model._parameters import free_parameters, with_free_parameters

if TYPE_CHECKING:
    from ._summary import FitResult


def _kalman_loss(theta, problem):
    """`-log L` (Kalman) at `theta` plus the prior's ½‖prior rows‖²."""
    s = _state(theta, problem)
    return kalman_nll(s.model, problem.data, s.run_initial) + 0.5 * jnp.sum(
        _prior(theta, problem) ** 2)


def _solve_kalman(theta0, problem, solver, max_steps: int):
    """`(theta, steps, converged)` from `newton` or an optimistix minimiser in at most
    `max_steps` iterations."""
    return _solve_kalman_jit(theta0, problem, *traced_settings(solver, max_steps))


@eqx.filter_jit
def _solve_kalman_jit(theta0, problem, solver, max_steps):
    if isinstance(solver, TruncatedNewton):
        sol = newton(_kalman_loss, theta0, problem, solver, max_steps)
        return sol.value, sol.num_steps, sol.converged
    sol = optx.minimise(_kalman_loss, solver, theta0, problem, max_steps=max_steps, throw=False)
    return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


@eqx.filter_jit
def _nll_and_hessian(theta, problem):
    """`-log L` and its Hessian in `theta` (free, free), for a problem without prior."""
    return _kalman_loss(theta, problem), jax.hessian(_kalman_loss)(theta, problem)


# Compiled once per structure: called eagerly, the simulator would trace anew every fit.
_simulate_jit = eqx.filter_jit(simulate_dataset)


def fit_kalman(prep: Prepared, start: Solution, solver, max_steps: int, prior_log_std: float,
               say) -> Solution:
    """The Kalman stage, warm-started from the output-error `start`."""
    index, names = prep.free("kalman")
    template = start.state
    theta0 = free_parameters(template, index)
    prior_mean = free_parameters(prep.template, index)  # the file's values
    solver = solver or TruncatedNewton()
    weight = 0.0 if isinstance(solver, TruncatedNewton) else 1.0 / prior_log_std
    sigma = start.problem.sigma[:len(prep.spec.sensors)]  # the filter's own noise is in theta
    problem = make_problem(template, index, prep.data, sigma, prior_mean, weight)
    say(f"Kalman likelihood: {len(names)} parameters, started from the output-error fit")
    theta, n_steps, converged = _solve_kalman(theta0, problem, solver, max_steps)
    _check_finite(theta, theta0, names)
    state = with_free_parameters(template, index, theta)
    problem = make_problem(template, index, prep.data, sigma, prior_mean)
    nll, info = _nll_and_hessian(theta, problem)
    predictions = _simulate_jit(state.model, prep.data, state.run_initial)
    return Solution(problem, np.asarray(theta), state, names, np.asarray(info), float(nll),
                    int(n_steps), bool(converged), np.asarray(predictions))


@eqx.filter_jit
def kalman_smoothed(model, data, run_initial):
    """RTS-smoothed node temperatures of every run: mean and std, each (runs, times,
    states) °C."""
    return kalman_runs(model, data, run_initial, lambda ts, kf: rts_smoother(model, ts, kf))


@eqx.filter_jit
def _innovations(model, data, run_initial):
    return kalman_runs(model, data, run_initial,
                       lambda ts, kf: kf.innovations / jnp.where(
                           kf.innovation_std > 0, kf.innovation_std, 1.0))


def standardized_innovations(result: FitResult) -> list[np.ndarray]:
    """Kalman fits: each run's one-step innovations over their std, (times, outputs), NaN
    where nothing was measured."""
    data = result.problem.data
    e = np.asarray(_innovations(result.model, data, result.state.run_initial))
    mask = np.asarray(data.mask)
    return [np.where(mask[r, :len(p)], e[r, :len(p)], np.nan)
            for r, p in enumerate(result.predictions)]
