"""The Kalman stage of a fit: the prediction-error likelihood, started from the file's
values or from an output-error fit (`_fit._kalman_stages` chooses).

The default `TruncatedNewton` leaves undetermined directions where they start; an
optimistix minimiser gets a weak Gaussian prior on `theta` around the file's values
instead (std `prior_log_std` in log units), left out of every reported likelihood.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._integration import (SUBSTEP_LADDER, fewest_kalman_substeps, shared_substeps,
                           with_substeps)
from ._likelihood import kalman_nll, kalman_runs, simulate_dataset
from ._newton import TruncatedNewton, newton
from ._problem import Prepared, Solution, _check_finite, _prior, _state, make_problem
from ._smoothed import kalman_smoothed
from ..compilation._traced_cache import stored_jit
from ..model._parameters import free_parameters, with_free_parameters

if TYPE_CHECKING:
    from ._fit_result import FitResult


def _kalman_loss(theta, problem):
    """`-log L` (Kalman) at `theta` plus the prior's ½‖prior rows‖²."""
    s = _state(theta, problem)
    return kalman_nll(s.model, problem.data, s.run_initial) + 0.5 * jnp.sum(
        _prior(theta, problem) ** 2)


def _solve_kalman(theta0, problem, solver, max_steps: int, pins=()):
    """`(theta, steps, converged)` from `newton` or an optimistix minimiser in at most
    `max_steps` iterations; `newton` leaves the parameters `pins` (held at zero by
    `problem`'s prior rows) out of its steps."""
    if isinstance(solver, TruncatedNewton):
        sol = _newton_except(theta0, problem, pins, solver, max_steps)
        return jax.device_put(sol.value), sol.num_steps, sol.converged
    return _minimise_jit(theta0, problem, solver, max_steps)


def _newton_except(theta0, problem, pins, solver, max_steps: int):
    """`newton` on the parameters of `theta0` not in `pins`, those held where they are.
    Held ones are left out, not just pinned by their prior rows: a pin's curvature
    (`_PIN`², 1e14) would set the eigendecomposition's rounding (1e-2) above the
    curvature of the directions the polish must follow."""
    theta = np.array(theta0, float)
    free = np.setdiff1d(np.arange(theta.size), np.asarray(pins, int))

    def full(z):
        t = theta.copy()
        t[free] = z
        return jax.device_put(t)

    def value_grad_information(z):
        v, g, info, _ = _value_grad_information(full(z), problem)
        return v, np.asarray(g)[free], np.asarray(info)[np.ix_(free, free)]

    sol = newton(value_grad_information, theta[free], solver, int(max_steps))
    theta[free] = sol.value
    return dataclasses.replace(sol, value=theta)


@eqx.filter_jit
def _minimise_jit(theta0, problem, solver, max_steps):
    sol = optx.minimise(_kalman_loss, solver, theta0, problem, max_steps=max_steps, throw=False)
    return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


def _value_grad_information(theta, problem):
    """`_scoring(theta, problem)`, from a program compiled without LLVM's optimizations
    where its calls are cheap (`_cheap_calls`), else from an optimized one."""
    return (_scoring_cheap if _cheap_calls(problem) else _scoring_optimized)(theta, problem)


# A linear model's scoring calls are cheap below this many samples × states²: compiled
# without LLVM's optimizations (`stored_jit`'s `once`), its program compiles in half the
# time and runs 30 % slower (PRBS1's three-state step-2 model, 1,691 samples: 0.36
# against 0.77 s, 6.5 against 5.0 ms a call), a gain for a structure's few hundred calls
# at most; the six-node IMU's (4,921 samples: 177,156, some 50 ms a call, 218 calls a
# fit) would lose 3 s. PRBS1's loop: 61.4 s against 65.0 s, two alternating pairs.
CHEAP_SCORING = 50_000


def _cheap_calls(problem) -> bool:
    model = problem.template.model
    n = model.network.topology.n_nodes
    return not model.is_nonlinear and np.size(problem.data.ts) * n * n <= CHEAP_SCORING


def _scoring(theta, problem):
    """`-log L` (with the prior rows), its gradient and the Fisher information in `theta`
    (free, free), from forward sensitivities through the filter (the method of scoring,
    Gupta & Mehra 1974): `g` is the tangent of `-log L` itself, exact; from those of
    every innovation `e_k` and its covariance `S_k`,

        I_ij = Σ_k (∂ᵢe)ᵀS⁻¹∂ⱼe + ½ tr(S⁻¹∂ᵢS S⁻¹∂ⱼS),

    each sum one matrix product (written as einsums over samples, they took a third of
    the IMU's call). `I` is the expected curvature given the past, the asymptotic inverse
    covariance of the estimate. One forward-mode program per structure (a third of the
    Hessian's compilation) for the steps, the boundary check, the polish and the final
    information; fourth, the standardized innovations `e_k / sqrt(diag S_k)` (runs,
    times, outputs; 0 where unmeasured), a solution's whiteness evidence."""
    def filtered(t):
        s = _state(t, problem)
        out = kalman_runs(s.model, problem.data, s.run_initial,
                          lambda ts, kf: (kf.innovations, kf.innovation_cov, kf.nll))
        return out, out

    (de, dS, dnll), (e, S, nll) = jax.jacfwd(filtered, has_aux=True)(theta)
    q = theta.shape[0]
    Sinv = jnp.linalg.inv(S)  # (runs, times, p, p); unmeasured rows are identity rows
    Sinv_de = jnp.einsum("rtij,rtjq->rtiq", Sinv, de)
    Sinv_dS = jnp.einsum("rtij,rtjkq->rtikq", Sinv, dS)
    # both sums over (runs, times, rows) as one matrix product each
    info = (de.reshape(-1, q).T @ Sinv_de.reshape(-1, q)
            + 0.5 * Sinv_dS.reshape(-1, q).T @ jnp.swapaxes(Sinv_dS, 2, 3).reshape(-1, q))
    prior, w = _prior(theta, problem), problem.prior_weight
    standardized = e / jnp.sqrt(jnp.diagonal(S, axis1=2, axis2=3))
    return (jnp.sum(nll) + 0.5 * jnp.sum(prior ** 2), jnp.sum(dnll, axis=0) + prior * w,
            info + jnp.diag(w ** 2), standardized)


_scoring_optimized = stored_jit(_scoring)
_scoring_cheap = stored_jit(_scoring, once=True)


def _nll(theta, problem) -> float:
    """`-log L` (with the prior rows) from the scoring program: a program of its own
    would cost its compilation for a handful of calls a fit."""
    return float(_value_grad_information(theta, problem)[0])


# Compiled once per structure: called eagerly, the simulator would trace anew every fit.
_simulate_jit = stored_jit(simulate_dataset, once=True)


def _compile_ahead(*programs) -> None:
    """Compile `programs` (`(stored_jit function, arguments)` pairs) on a background
    thread while the fit runs compiled code, which releases the GIL: on two cores the
    end of a fit is then not followed by its free run's and smoother's compilation (2-3 s
    for the six-node IMU). Not while the fit compiles: XLA's compilations compete. The
    fit's own calls wait for these compilations instead of repeating them; a failure
    here is left for them to report."""
    def compile_all():
        try:
            for function, args in programs:
                function.ahead(*args)
        except Exception:  # noqa: BLE001  (the same call on the fit's thread raises it)
            pass

    threading.Thread(target=compile_all, name="thermojax-compile-ahead").start()


def fit_kalman(prep: Prepared, start: Solution | None, solver, max_steps: int,
               prior_log_std: float, say, polish: bool = True,
               nested_nll: float | None = None, smoothed: bool = False) -> Solution:
    """The Kalman stage, started from the output-error `start` or, with `start` None,
    from the file's values; `polish` False ends it after the scoring steps and the boundary
    check, as does a start that ends far above `nested_nll` (`fit`'s); `smoothed` as
    `fit`'s. A nonlinear model is integrated in the fewest substeps (of the extended
    filter's fourth-order step, `_likelihood._extended_transition`) its likelihood needs
    at the start (`_integration.fewest_kalman_substeps`), and solved again from the
    solution with more as long as the solution needs more."""
    template = prep.template if start is None else start.state
    p = len(prep.spec.sensors)  # the filter's own noise is in theta; sigma rides along
    sigma = prep.sigma[:p] if start is None else start.problem.sigma[:p]
    say(f"Kalman likelihood: {len(prep.free('kalman')[1])} parameters, started from "
        + ("the file's values" if start is None else "the output-error fit"))
    if not template.model.is_nonlinear:
        return _fit_kalman_from(prep, template, sigma, solver, max_steps, prior_log_std, say,
                                polish, nested_nll, smoothed)
    used = _kalman_substeps(template, prep.data, remember=False)
    while True:  # at most once per rung of the ladder
        sol = _fit_kalman_from(prep, with_substeps(template, used), sigma, solver,
                               max_steps, prior_log_std, say, polish, nested_nll, smoothed,
                               finer=lambda state: _kalman_substeps(state, prep.data))
        # what the solution needs (remembered), or the unpolished end already checked
        more = (sol.substeps if isinstance(sol, _Unpolished)
                else _kalman_substeps(sol.state, prep.data))
        if more <= used:
            return sol
        say(f"the solution's likelihood needs {more} integration substeps per sample period "
            f"(its start's {used}); solving again from it with {more}")
        template, used = sol.state, more


# The most substeps a Kalman fit starts in, whatever its start needs: a start far
# from the data (the user's values, an effect at its score's estimate) can need 16 where
# its solution needs 2-8, and a solve in 16 costs four times one in 4 a call (PRBS1). The
# solution's check decides whether the fit is solved again, from there, in more.
START_SUBSTEPS = 4


def _kalman_substeps(state, data, remember: bool = True) -> int:
    """The substeps a Kalman fit of `state`'s structure takes from here: at a
    solution (`remember`, for later fits of the structure too) the fewest its likelihood
    needs, at a start at most `START_SUBSTEPS` (where its filter is finite)."""
    substeps, _ = fewest_kalman_substeps(
        state, data, at_most=SUBSTEP_LADDER[-1] if remember else START_SUBSTEPS)
    return shared_substeps(state.model, substeps, kalman=True, remember=remember)


@dataclasses.dataclass(frozen=True)
class _Unpolished:
    """Where a nonlinear model's fit stopped before its polish (`state`, a `FitState`):
    its likelihood there needs `substeps`, more than it was solved in."""

    state: object
    substeps: int


def _fit_kalman_from(prep: Prepared, template, sigma, solver, max_steps: int,
                     prior_log_std: float, say, polish: bool, nested_nll=None,
                     smoothed: bool = False, finer=None) -> Solution | _Unpolished:
    """`fit_kalman` from the values of `template` (a `FitState`), integrated as it is.
    `finer(state) -> int`: the substeps a nonlinear model's likelihood needs at
    `state`, asked after the boundary check: where that is more than `template` is
    integrated in, the fit stops before its polish (`_Unpolished`), which would refine
    the optimum of a likelihood off by more than it gains (on PRBS1 the heater mass's
    first start needs 8 once its boundary check holds a process noise at zero, 4
    before it; its polish in 4, 3 s, gained 0.08 where 4 substeps are 0.09 off). Where
    the polish itself moves the solution to a need of more, `fit_kalman`'s check of
    the solution still solves it again."""
    index, names = prep.free("kalman")
    theta0 = free_parameters(template, index)
    prior_mean = free_parameters(prep.template, index)  # the file's values
    solver = solver or TruncatedNewton()
    weight = 0.0 if isinstance(solver, TruncatedNewton) else 1.0 / prior_log_std
    problem = make_problem(template, index, prep.data, sigma, prior_mean, weight)
    theta, n_steps, converged = _solve_kalman(theta0, problem, solver, max_steps)
    _check_finite(theta, theta0, names)
    run = (template.model, prep.data, template.run_initial)  # once the steps' are compiled
    _compile_ahead((_simulate_jit, run), *([(kalman_smoothed, run)] if smoothed else []))
    at_zero = []
    if isinstance(solver, TruncatedNewton) and converged:  # max_steps hit: stop there
        plain = make_problem(template, index, prep.data, sigma, prior_mean)
        nll, _, hess = (np.asarray(a) for a in _value_grad_information(theta, plain)[:3])
        gain, polished = 0.0, True
        if polish and nested_nll is not None and not _within_reach(nll, nested_nll, say):
            # a local optimum far above a likelihood the model reaches: its boundary check
            # could not bring it back either (PRBS1's heater mass from the user's values,
            # 1,894 above: 1.3 s in 8 substeps for nothing)
            at_zero, steps, polish = [], 0, False
            polished = False
        else:
            theta, at_zero, steps, nll = _zero_variances(theta, plain, names, solver,
                                                         max_steps, say, at=(nll, hess))
            if polish and nested_nll is not None:
                polish = polished = _within_reach(nll, nested_nll, say)
        if polish and finer is not None:
            state = with_free_parameters(template, index, theta)
            more = finer(state)
            if more > template.model.etd2_substeps:
                return _Unpolished(state, more)
        if polish:
            theta, gain, polished = _polish(theta, plain, names, at_zero, say, last=False)
        for k in range(_RESCORE_ROUNDS):  # far from where scoring stopped: the boundary
            if gain <= _RESCORE:  # check and scoring again (the polish walks noises down)
                break
            theta, at_zero, more, _ = _zero_variances(theta, plain, names, solver,
                                                      max_steps, say, at_zero)
            steps += more
            theta, more, converged = _solve_kalman(theta, _pinned(plain, at_zero), solver,
                                                   max_steps, at_zero)
            theta, gain, polished = _polish(theta, plain, names, at_zero, say,
                                            last=k + 1 == _RESCORE_ROUNDS)
            steps += more
        n_steps += steps
        converged = converged and polished
    state = with_free_parameters(template, index, theta)
    problem = make_problem(template, index, prep.data, sigma, prior_mean)
    nll, _, info, standardized = _value_grad_information(theta, problem)
    info = np.array(info)
    if at_zero:  # held on the boundary: known, not estimated; decoupled, never "weak"
        top = float(np.max(np.diag(info)))
        info[at_zero, :] = info[:, at_zero] = 0.0
        info[at_zero, at_zero] = top
    predictions = _simulate_jit(state.model, prep.data, state.run_initial)
    return Solution(problem, np.asarray(theta), state, names, info, float(nll),
                    int(n_steps), bool(converged), np.asarray(predictions),
                    at_bound=tuple(names[i] for i in at_zero),
                    innovations=np.asarray(standardized))


# −log L above a nested model's at which the scoring steps' end is a local optimum that
# the polish does not leave: the polish gains hundredths to tenths where the steps stop
# near an optimum, and on PRBS1 8.9 in 215 s from a start 1894 above its nested model.
_BEYOND_POLISH = 10.0


def _within_reach(nll: float, nested_nll: float, say) -> bool:
    """Whether the scoring steps ended within `_BEYOND_POLISH` of a −log L the model is
    known to reach (`fit`'s `nested_nll`), else say why not polished."""
    if nll <= nested_nll + _BEYOND_POLISH:
        return True
    say(f"the scoring steps ended at -log L {nll:.2f}, {nll - nested_nll:.2f} above a "
        "likelihood the model reaches: a local optimum, not polished")
    return False


# A variance held at zero: the log of the smallest value a model file's zero becomes
# (`ThermalModel.from_spec`), pinned through the prior rows (no new compilation).
_LOG_ZERO = math.log(1e-12)
_PIN = 1e7
_AT_ZERO = 1e-6  # log units: a variance within this of `_LOG_ZERO` is already held at zero
_ZERO_TOL = 1e-3  # −log L a zero may cost and still be taken: it sits on the boundary
# A polish gain (−log L) beyond which the scoring steps restart from the polished point:
# a variance far below its optimum has too little information (∝ q⁴ in log q) for a
# scoring step to move it, which the polish's descent does not need.
_RESCORE = 0.1
_RESCORE_ROUNDS = 3
# The polish's Newton steps: every direction with curvature (in −log L per parameter
# unit squared) above this is stepped along, and they stop where the predicted decrease
# is below `_POLISH_TOL` (a hundredth of the truncated solver's `tol`).
_POLISH_CURVATURE = 1e-6
_POLISH_TOL = 1e-4
_POLISH_STEPS = 60


def _pinned(problem, pins: list[int]):
    """`problem` with the parameters `pins` held at zero (`_LOG_ZERO`)."""
    mean = np.array(problem.prior_mean)
    weight = np.zeros_like(mean)
    mean[pins] = _LOG_ZERO
    weight[pins] = _PIN
    return make_problem(problem.template, problem.index, problem.data, problem.sigma, mean,
                        weight)


def _zero_variances(theta, problem, names, solver, max_steps, say, pins=(), at=None):
    """The boundary check of variances whose optimum may be zero (docs/extensions.md):
    each process noise the likelihood barely determines (curvature in log q below the
    solver's `min_curvature`), smallest first, is held at zero and the rest refitted; the
    zero is kept when −log L does not rise by more than `_ZERO_TOL`. `at`: `(−log L,
    information)` at `theta` when already computed.

    **Returns:** `(theta, indices held at zero, Newton steps taken, −log L there)`."""
    if at is None:
        nll, _, hess = (np.asarray(a) for a in _value_grad_information(theta, problem)[:3])
    else:
        nll, hess = at
    theta = np.array(theta)
    pins, steps = list(pins), 0
    candidates = [i for i, n in enumerate(names) if n.endswith(".process_noise")
                  and hess[i, i] < solver.min_curvature and i not in pins]
    for i in sorted(candidates, key=lambda i: theta[i]):
        if abs(theta[i] - _LOG_ZERO) <= _AT_ZERO:
            # already at zero (a warm start from a fit that held it there: a held-out
            # fold, a re-solve in more substeps): held there as it is, −log L unchanged,
            # without a solve (on PRBS1 two of these cost each fold of the heater mass
            # 0.7-1.0 s in 8 substeps)
            say(f"{names[i]} held at zero, where it starts")
            theta[i] = _LOG_ZERO
            pins.append(i)
            continue
        trial = theta.copy()
        trial[i] = _LOG_ZERO
        pinned = _pinned(problem, pins + [i])
        new, n, _ = _solve_kalman(jax.device_put(trial), pinned, solver, max_steps,
                                   pins + [i])
        steps += int(n)
        new_nll = _nll(new, problem)
        if np.isfinite(new_nll) and new_nll <= float(nll) + _ZERO_TOL:
            say(f"{names[i]} held at zero: -log L {float(nll):.3f} -> {new_nll:.3f}")
            pins.append(i)
            theta, nll = np.asarray(new), new_nll
    return jax.device_put(theta), pins, steps, float(nll)


def _polish(theta, problem, names, pins, say, tol: float = 1e-3, last: bool = True):
    """Confirm the optimum from the truncated solution, on the parameters not held at
    zero: Newton steps along every direction (the scoring steps' curvature, untruncated
    down to `_POLISH_CURVATURE`, damped as in `newton`), then, if they do not converge
    in `_POLISH_STEPS`, L-BFGS-B (SciPy) from where they stopped, unless a round of
    boundary check and scoring follows (not `last`) and the steps gained more than
    `_RESCORE`: that round goes on from there at a fraction of L-BFGS-B's calls. Taken
    if it lowers −log L.

    **Returns:** `(theta, gain in −log L, ok)`; `ok` (the fit is then reported converged)
    when it found nothing better than `tol`, or moved and met a convergence test (the
    Newton steps' predicted decrease below `_POLISH_TOL`, or L-BFGS-B's projected
    gradient below `gtol` or no relative progress)."""
    import scipy.optimize

    pinned = _pinned(problem, pins)
    theta = np.array(theta, float)
    full = TruncatedNewton(min_curvature=_POLISH_CURVATURE, tol=_POLISH_TOL)
    sol = _newton_except(theta, pinned, pins, full, _POLISH_STEPS)
    start = sol.initial_loss  # the steps' first evaluation, at `theta`
    if sol.loss < start:
        theta = np.array(sol.value, float)
    ok = sol.converged
    if not ok and not last and start - sol.loss > _RESCORE:
        say(f"polish (Newton, not converged): -log L lower by {start - sol.loss:.4f}")
        return jax.device_put(theta), start - sol.loss, False
    if not ok:
        free = np.setdiff1d(np.arange(theta.size), pins)
        _, _, info, _ = _value_grad_information(jax.device_put(theta), pinned)
        # in units of each parameter's std (curvature floored at 1, a log unit): the
        # curvatures of a fit span ten decades, which L-BFGS-B alone crawls through
        scale = 1.0 / np.sqrt(np.maximum(np.diag(np.asarray(info))[free], 1.0))

        def f(z):
            full = theta.copy()
            full[free] += z * scale
            v, g, _, _ = _value_grad_information(jax.device_put(full), pinned)
            g = np.asarray(g)[free] * scale
            return (float(v), g) if np.isfinite(v) and np.all(np.isfinite(g)) else (1e300,
                                                                                   0 * g)

        res = scipy.optimize.minimize(f, np.zeros(free.size), jac=True, method="L-BFGS-B",
                                      options=dict(maxiter=200, ftol=1e-12, gtol=1e-6))
        if res.fun < min(start, sol.loss):
            theta[free] += res.x * scale
        ok = res.success
    final = min(start, sol.loss, float(res.fun) if not sol.converged else np.inf)
    if not final < start:
        return jax.device_put(np.array(theta)), 0.0, True
    gain = start - final
    say(f"polish ({'Newton' if sol.converged else 'Newton, then L-BFGS-B'}): -log L lower "
        f"by {gain:.4f}")
    return jax.device_put(theta), gain, bool(gain < tol or ok)


def standardized_innovations(result: FitResult) -> list[np.ndarray]:
    """Kalman fits: each run's one-step innovations over their std, (times, outputs), NaN
    where nothing was measured (from the fit's last scoring call: no program of its own)."""
    data = result.problem.data
    e = result.innovations
    mask = np.asarray(data.mask)
    return [np.where(mask[r, :len(p)], e[r, :len(p)], np.nan)
            for r, p in enumerate(result.predictions)]
