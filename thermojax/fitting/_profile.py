"""Profile-likelihood confidence intervals of output-error fits."""

from __future__ import annotations

import numpy as np

from .._errors import InputError
from ._normal_equations import METHOD as NORMAL_EQUATIONS
from ._output_error import _chi_square, _solve_oe
from ._problem import _is_log, make_problem
from ._solver import TruncatedGaussNewton
from ._summary import FitResult


def profile_interval(result: FitResult, name: str, level: float = 0.95, max_refits: int = 24,
                     ends_theta: list | None = None) -> tuple[float | None, float | None]:
    """Profile-likelihood confidence interval of one free parameter (output error).

    The parameter is pinned at trial values (a stiff prior row in the same compiled
    problem) while every other free parameter is refitted; the interval's ends are
    where `2 (nll_pinned - nll_min)` reaches the chi-square(1) quantile of `level`,
    found by bracketing and bisection (`max_refits` refits per end at most). Noise stds
    stay at their fitted values. An end that never reaches the threshold (an
    unidentifiable side) is None. An effect parameter fitted through a lowered entry (a
    sensor lag's `tau` as the conductance `C / tau`) is profiled in that entry and its
    ends mapped back.

    `ends_theta`: a list that, when given, receives the refitted `theta` (every free
    parameter, `result.free_names` order) at the refit nearest each end found, lower then
    upper (None for an open end): what the other parameters did as this one moved.

    **Returns:** `(lower, upper)` in the parameter's physical units.
    """
    from scipy.stats import chi2

    if result.likelihood != "output_error" or result.problem is None:
        raise InputError("profile intervals are available for output-error fits; refit with "
                         "likelihood='output_error'.", field="--profile")
    if result.method.startswith(NORMAL_EQUATIONS):
        raise InputError("a profile likelihood refits the model holding the residuals' "
                         "Jacobian, which this fit on a long log avoided (normal equations "
                         "summed over stretches of the log); fit a shorter stretch of the "
                         "log to profile a parameter.", field="--profile")
    if name not in result.free_names:
        raise InputError(f"'{name}' is not a free parameter; free ones are {result.free_names}.",
                         field="--profile")
    j = result.free_names.index(name)
    problem, theta_hat = result.problem, np.asarray(result.theta)
    threshold = float(chi2.ppf(level, 1))
    base = _chi_square(theta_hat, problem)
    pin = np.zeros_like(theta_hat)
    pin[j] = 1e7

    refits: dict[float, np.ndarray] = {}

    def excess(value: float) -> float:
        start = theta_hat.copy()
        start[j] = value
        pinned = make_problem(problem.template, problem.index, problem.data, problem.sigma,
                              start, pin, bias=problem.bias)
        theta = _solve_oe(start, pinned, TruncatedGaussNewton(), 100)[0]
        refits[value] = np.asarray(theta)
        return _chi_square(theta, problem) - base - threshold

    std = result.parameters[name]["std"]
    value = float(theta_hat[j])
    log = _is_log(name)
    step = (std / result.parameters[name]["value"] if log else std) if std else 0.5
    ends = [_end(excess, value, sign, 1.96 * step, max_refits) for sign in (-1.0, 1.0)]
    if ends_theta is not None:
        ends_theta.extend(None if e is None else refits[min(refits, key=lambda v: abs(v - e))]
                          for e in ends)
    ends = [None if e is None else float(np.exp(e)) if log else e for e in ends]
    if name in result.lowered_as:  # value = scale * lowered ** power, monotone
        scale, power = result.lowered_as[name]
        ends = [None if e is None else scale * e ** power for e in ends]
        if power < 0:
            ends = ends[::-1]
    return ends[0], ends[1]


def _end(excess, value: float, sign: float, width: float, max_refits: int) -> float | None:
    """Where `excess` crosses zero on one side of `value` (in theta units): bracketed by
    doubling steps from `width`, then bisected to 1e-3 of `width`; None if unbracketed."""
    lo, hi, tol, refits = value, None, 1e-3 * width, 0
    while refits < max_refits:
        trial = value + sign * width
        refits += 1
        if excess(trial) > 0:
            hi = trial
            break
        lo, width = trial, width * 2
    if hi is None:
        return None
    for _ in range(max(0, max_refits - refits)):
        mid = 0.5 * (lo + hi)
        if abs(hi - lo) < tol:  # relative to the expected half-width
            break
        if excess(mid) > 0:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)
