"""Prediction-error fitting of a model to several runs: output error or Kalman likelihood.

`fit(spec, experiments, likelihood=...)` follows `optx.least_squares(fn, solver, y0, args)`
and is a pipeline of three stages, each in the file that owns its concept:

1. `_problem.prepare`: lower structural effects, check and pad the runs, lay out the
   flat vector `theta` the optimizer sees (logs of positive parameters, initial
   temperatures in °C);
2. solve: `_output_error.fit_output_error` (truncated Gauss-Newton on weighted
   free-run residuals, estimated noise stds at their ML values throughout); for the Kalman
   likelihood `_kalman_fit.fit_kalman`, from the file's values and, when that does not
   converge, again from the output-error fit (`_kalman_stages`);
3. `_summary.summarize`: a `FitResult` with values by name, stds, metrics,
   identifiability and (Kalman) smoothed states.

The residual and loss functions are module-level and take everything through `args`,
so a second fit of the same structure (another unit, another candidate effect) reuses
the compilation.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ..measurements._data import Experiment
from ..model._spec import ModelSpec
from .._errors import InputError
from ._kalman_fit import fit_kalman, standardized_innovations
from ._output_error import fit_output_error, output_error_at
from ._initial_states import start_mismatches
from ._problem import (LIKELIHOODS, SHORT_RUN, Solution, integrated_for_output_error,
                       prepare)
from ._adjoint import adjoint_eligible, fit_adjoint
from ._normal_equations import METHOD as NORMAL_EQUATIONS, fit_normal_equations
from ._size import check_fit_size, choose_path
from ._plateau import GAIN, invisible_nodes, plateau_note, visible_start
from ._profile import profile_interval
from ._summary import FitResult, summarize

#: s; a fit predicted to take longer says so before it starts (`fitting._size`).
LONG_FIT_S = 120.0
#: How an output-error fit may differentiate its residuals (`fit`'s `jacobian`).
JACOBIANS = ("auto", "forward", "adjoint", "normal_equations")

__all__ = ["FitResult", "LIKELIHOODS", "fit", "output_error_at", "profile_interval",
           "standardized_innovations"]


def fit(spec: ModelSpec, experiments: list[Experiment], *, likelihood: str = "output_error",
        solver=None, max_steps: int = 100, prior_log_std: float = 3.0, n_starts: int = 1,
        seed: int = 0, progress=None, holdout: int | tuple | None = None,
        restart_plateaus: bool = True, polish: bool = True,
        nested_nll: float | None = None, smoothed: bool = False,
        restart_unconverged: bool = True, starts: dict | None = None,
        jacobian: str = "auto") -> FitResult:
    """Fit the free parameters of `spec` to several runs at once.

    **Arguments:**

    - `spec`: the model (its fixed/free flags say what is estimated).
    - `experiments`: one `Experiment` per run; parameters are shared, each run
      has its own initial state.
    - `likelihood`: `"output_error"` (truncated Gauss-Newton on free-run residuals
      weighted by each sensor's noise; estimated noise stds held at their ML
      values throughout the solve: the likelihood profiled over them) or `"kalman"` (truncated Newton steps with the
      Fisher information, i.e. scoring, on the Kalman prediction-error likelihood,
      started from the output-error fit).
    - `solver`: default `TruncatedGaussNewton()` for output error and
      `TruncatedNewton()` for Kalman; an optimistix least-squares solver (output
      error) or minimiser (Kalman) may be passed instead.
    - `max_steps`: iterations at most of every solve (each output-error pass and the
      Kalman solve), whichever the solver; a fit that hits it reports `converged` False.
    - `prior_log_std`: std (log units) of the weak prior that keeps unidentifiable
      directions at their starting values when an optimistix minimiser fits the
      Kalman likelihood (the truncated solvers need none).
    - `n_starts`: more than 1 adds starts perturbed by a log-normal factor
      (std 0.5); the best likelihood wins. `seed` seeds them.
    - `progress`: optional callable taking a one-line string.
    - `holdout`: index of a run left out of the likelihood (its measurements are masked;
      it is still simulated, so `predictions` hold its out-of-sample prediction), or
      `(run, (start, stop))`, a block of that run's samples left out likewise.
    - `restart_plateaus`: when the fit stops with a node's time constant far outside the
      data's time scales and its parameters unidentifiable, fit again with that node at
      a time constant the data can see and keep the better (`_plateau`); the message
      says which happened.
    - `polish`: Kalman fits with the default solver confirm the scoring steps' optimum
      along the valleys they crawl (Newton steps on every curvature, then L-BFGS-B:
      docs/extensions.md). False leaves that out: a fit warm-started at a nearby optimum
      (a held-out fold's, from the fit to all the data) whose last few 0.1 of −log L do
      not matter.
    - `nested_nll`: a −log L `spec` is known to reach: a nested model's (`spec` without an
      effect, which `spec` reaches with the effect at zero), or for a plateau restart the
      first fit's. A Kalman start whose scoring steps end far above it is in a local
      optimum: it is neither checked at its variances' boundary nor polished, and the
      fit goes on as from a start that did not converge.
    - `restart_unconverged`: a Kalman fit with the default solver that does not converge
      from the file's values is fitted again from the output-error fit (the better of
      the two is kept). False returns the unconverged fit (a failure raises): one start
      among several that are fitted anyway (an investigation's refit starts).
    - `starts`: node -> each run's start (°C, (runs,)) for the nodes whose start is
      estimated, instead of their first readings (`fitting._initial_states`); a held-out
      fit passes the full fit's estimates, which data after a held-out first block
      cannot determine.
    - `jacobian`: how the output-error fit differentiates its residuals. `"auto"`: by
      forward sensitivities (the Jacobian formed), except for a linear network without
      bias columns, fitted with the default solver (`fitting._size.choose_path`): on a
      long log whose residuals' Jacobian would take more than
      `_size.NORMAL_EQUATIONS_ABOVE_BYTES`, on normal equations summed over stretches
      of the log (`fitting._normal_equations`: memory independent of the log's length);
      for a network whose forward sensitivities would take longer than a minute or not
      fit in memory, by the adjoint path (`fitting._adjoint`: reverse-mode products,
      matrix-free steps, never a Jacobian). `"forward"`, `"adjoint"` or
      `"normal_equations"` forces one; the report's `method` says which ran.
    - `smoothed`: Kalman fits whose `FitResult.smoothed` (RTS-smoothed node temperatures)
      will be read: their program is compiled beside the fit's last steps, where it
      costs no wall time on two cores. Otherwise they are computed when first read.

    **Returns:** a `FitResult`.
    """
    t_start = time.perf_counter()
    say = progress or (lambda _msg: None)
    prep = prepare(spec, experiments, likelihood, holdout, starts)
    n_states = prep.template.model.network.topology.n_nodes
    sizes = dict(n_samples=int(sum(prep.data.lengths)), n_readings=int(prep.data.outputs.size))
    if jacobian not in JACOBIANS:
        raise InputError(f"`fit(jacobian={jacobian!r})`: expected one of "
                         f"{', '.join(JACOBIANS)}.", file=spec.source)
    eligible = adjoint_eligible(prep, likelihood, solver)
    path = jacobian if jacobian in ("adjoint", "normal_equations") else choose_path(
        n_states, len(prep.names), eligible and jacobian != "forward", **sizes)
    if path != "forward" and not eligible:
        raise InputError(f"`fit(jacobian={path!r})` needs an output-error fit of a linear "
                         "model without bias columns, with the default solver; use "
                         "jacobian='auto'.", file=spec.source)
    cost = check_fit_size(n_states, len(prep.names), spec.source, path=path, **sizes)
    if path == "normal_equations":
        say(f"a long log: {sizes['n_readings']:,} sensor readings and {len(prep.names)} "
            "free parameters, fitted on normal equations summed over stretches of the log "
            f"(about {cost.bytes / 1e9:.1f} GB and roughly {_duration(cost.seconds)} on a "
            "2-core machine)")
    elif path == "adjoint":
        say(f"a large network: {len(prep.names)} free parameters of {cost.n_states} "
            f"states, fitted by the adjoint path (about {cost.bytes / 1e9:.1f} GB and "
            f"roughly {cost.seconds / 60:.0f} min on a 2-core machine)")
    elif cost.seconds > LONG_FIT_S:
        say(f"a large fit: {len(prep.names)} free parameters of {cost.n_states} states, "
            f"about {cost.bytes / 1e9:.1f} GB and roughly {cost.seconds / 60:.0f} min on a "
            "2-core machine (fixing parameters known from design shortens it)")
    kalman = likelihood == "kalman"
    if kalman:
        sol = _kalman_stages(prep, solver, max_steps, prior_log_std, n_starts, seed, say,
                             polish, nested_nll, smoothed, restart_unconverged)
    elif path in ("adjoint", "normal_equations"):
        if n_starts > 1:
            say(f"the {path.replace('_', ' ')} path fits from the file's values only "
                "(one start)")
        fit_path = fit_adjoint if path == "adjoint" else fit_normal_equations
        sol, method = fit_path(prep, max_steps, say)
        sol.method = method
    else:
        sol = fit_output_error(prep, solver, max_steps, n_starts, seed, say)
    result = summarize(prep, sol, likelihood, t_start)
    if restart_plateaus:
        result = _off_plateau(result, experiments, say, likelihood=likelihood, solver=solver,
                              max_steps=max_steps, prior_log_std=prior_log_std,
                              n_starts=n_starts, seed=seed, holdout=holdout,
                              nested_nll=nested_nll, smoothed=smoothed,
                              restart_unconverged=restart_unconverged, starts=starts,
                              jacobian=jacobian)
        result.wall_time_s = time.perf_counter() - t_start
    say(f"fit done: -log L = {result.nll:.2f}, {result.n_params} parameters, {result.message}")
    if not kalman:  # a Kalman free run drifts with its process noise: no start check
        _warn_start_mismatch(result, experiments)
    return result


def _duration(seconds: float) -> str:
    """`seconds` in words: "40 s", "12 min"."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def _warn_start_mismatch(result: FitResult, experiments) -> None:
    """Warn where a run's first readings are far from the fitted model's start."""
    columns = result.lowered_spec.sensor_columns
    noise = {c: result.parameters.get(f"sensors.{c}.noise", {}).get("value") for c in columns}
    # a run with an estimated start moved it where the data say: nothing to warn of
    fixed = [e if not any(n.startswith(f"runs.{r}.") and n.endswith(".initial")
                          for n in result.free_names) else None
             for r, e in enumerate(experiments)]
    for message in start_mismatches(result.spec, columns, noise, result.predictions,
                                    fixed):
        warnings.warn(message, stacklevel=3)


def _off_plateau(result: FitResult, experiments, say, **options) -> FitResult:
    """`result`, or a refit from a start where its invisible nodes are visible when that
    fits better by `GAIN` (`_plateau`); either way the message says what was found."""
    invisible = invisible_nodes(result.spec, result.identifiability.unidentifiable_parameters,
                                min(e.dt for e in experiments),
                                max(float(e.ts[-1] - e.ts[0]) for e in experiments))
    if not invisible:
        return result
    if result.method.startswith(NORMAL_EQUATIONS):
        # a restart from far crawls without the geodesic acceleration (2·10⁶ samples of
        # the six-node IMU: over 100 steps, 6 minutes, for no gain)
        result.message += plateau_note(invisible, None, restarted=False)
        return result
    say(f"{invisible[0].describe()}: the data cannot move its parameters there; refitting "
        "from a time constant they can see")
    # the model reaches the first fit's likelihood: a Kalman restart that ends its scoring
    # steps far above it is a local optimum, not polished (as one far above a nested model)
    reached = result.nll if options.get("nested_nll") is None else min(result.nll,
                                                                       options["nested_nll"])
    options = {**options, "nested_nll": reached}
    with warnings.catch_warnings():  # its start is ours, not the user's: not warned about
        warnings.filterwarnings("ignore", message=f".*{SHORT_RUN}")
        again = fit(visible_start(result.spec, invisible), experiments, progress=say,
                    restart_plateaus=False, **options)
    gain = result.nll - again.nll
    if np.isfinite(gain) and gain > GAIN:
        again.message += plateau_note(invisible, gain)
        return again
    result.message += plateau_note(invisible, None)
    return result


def _kalman_stages(prep, solver, max_steps, prior_log_std, n_starts, seed, say,
                   polish=True, nested_nll=None, smoothed=False,
                   restart_unconverged=True) -> Solution:
    """The Kalman likelihood's solution. The default solver starts from the file's values
    (one compiled program fewer than an output-error stage first: a third of a first
    fit's time) and only when that does not converge (or diverges) again from the
    output-error fit, keeping the better of the two; multi-start (`n_starts` > 1) and
    optimistix minimisers always start from the output-error fit. Without
    `restart_unconverged` the fit from the file's values is the answer, converged or
    not."""
    direct = None
    if solver is None and n_starts == 1:
        try:
            direct = fit_kalman(prep, None, solver, max_steps, prior_log_std, say, polish,
                                nested_nll, smoothed)
        except InputError as err:  # diverged from the file's values
            if not restart_unconverged:
                raise
            why = f"failed ({err})"
        else:
            if direct.converged or not restart_unconverged:
                return direct
            why = "did not converge"
        say(f"Kalman fit from the file's values {why}; trying again from the output-error fit")
    start = fit_output_error(integrated_for_output_error(prep), None, max_steps, n_starts,
                             seed, say)
    try:
        sol = fit_kalman(prep, start, solver, max_steps, prior_log_std, say, polish,
                         nested_nll, smoothed)
    except InputError:
        if direct is None:
            raise
        return direct
    if direct is not None and np.isfinite(direct.nll) and direct.nll < sol.nll:
        return direct
    return sol
