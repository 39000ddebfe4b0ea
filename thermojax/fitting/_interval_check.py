"""Wald intervals checked against the profile likelihood where the quadratic picture may
fail (output error).

A Wald interval, value ± 1.96 std (on the log scale for a positive parameter), reads the
curvature at the optimum only. It can be confident where the data are not: when the
curvature is weak (the log-likelihood is far from quadratic over the interval) or when
the model has a near-null direction (mass can move into an unmeasured node, and the
likelihood is flat far from the optimum). There `check_intervals` computes the
profile-likelihood interval (`profile_interval`), says whether the two agree, and names
the parameters that moved with the profiled one at its interval's ends: those it trades
against.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from ._normal_equations import METHOD as NORMAL_EQUATIONS
from ._profile import profile_interval
from ._summary import FitResult

Z95 = 1.959963984540054  # the two-sided 95 % normal quantile
WEAK_RELATIVE = 0.2  # a relative Wald std above this is weak curvature
MAX_PROFILED = 8  # the weakest this many parameters at most
AGREE = 0.25  # each end within this fraction of the Wald half-width (θ units): agreement
MOVED_STDS = 1.0  # a partner moved more than its own std (|ρ| ≳ 0.5 with it) ...
MOVED_RELATIVE = 0.1  # ... and more than 10 % (or 0.1 of a non-positive parameter's scale)
#: s; after the first check, no further one starts when it is expected (at the mean cost
#: of those done) to end past this. A check refits the model at a dozen or more pinned
#: values: on the six-node IMU at 10⁶ samples each took about 3 minutes, eight of them 25.
BUDGET_S = 120.0


def intervals_to_check(result: FitResult) -> dict[str, str]:
    """Free parameters whose Wald interval needs the profile check -> why (words), the
    weakest first, at most `MAX_PROFILED`. Initial temperatures and unidentifiable
    parameters (already reported without a std) are left out."""
    if result.likelihood != "output_error" or result.problem is None:
        return {}
    near_null = bool(result.identifiability.directions)
    found = []
    for name in result.free_names:
        p = result.parameters.get(name) or {}
        value, std = p.get("value"), p.get("std")
        if name.endswith(".initial") or std is None or not value:
            continue
        relative = abs(std / value)
        if relative > WEAK_RELATIVE:
            found.append((relative, name, f"weak curvature (relative std {relative:.2g})"))
        elif near_null:
            found.append((relative, name, "the model has a near-null direction"))
    found.sort(reverse=True)
    return {name: why for _, name, why in found[:MAX_PROFILED]}


def check_intervals(result: FitResult, say=None, level: float = 0.95,
                    budget_s: float = BUDGET_S) -> dict[str, dict]:
    """The profile check of every parameter `intervals_to_check` names: name ->
    `{level, lower, upper, wald_lower, wald_upper, why, agrees, trades_with}` (physical
    units; an open profile end is None and never agrees).

    After the first, checks start while they are expected (at the mean cost of those
    done) to end within `budget_s` of the first's start; those left out,
    and all of them after a fit on summed normal equations (a profile's refits would hold
    the residuals' Jacobian that fit avoided), are warned about by name with how to ask
    for one."""
    say = say or (lambda _msg: None)
    todo = intervals_to_check(result)
    if not todo:
        return {}
    if result.method.startswith(NORMAL_EQUATIONS):
        warnings.warn(
            f"the Wald intervals of {', '.join(todo)} are not checked against the profile "
            "likelihood: on a log this long each check would refit the model holding the "
            "residuals' Jacobian, which the fit avoided. Fit a shorter stretch of the log "
            "to check them.", stacklevel=2)
        return {}
    theta_hat = np.asarray(result.theta)
    stds = _theta_stds(result)
    out = {}
    t0, per_check = time.perf_counter(), 0.0
    for i, (name, why) in enumerate(todo.items()):
        if i and time.perf_counter() - t0 + per_check > budget_s:
            left = list(todo)[i:]
            warnings.warn(
                f"profile checks stopped after {i} of {len(todo)}: each takes about "
                f"{per_check:.0f} s on these data, so the Wald intervals of "
                f"{', '.join(left)} stand unchecked; `--profile NAME` checks one.",
                stacklevel=2)
            break
        say(f"profile check {i + 1}/{len(todo)}: {name} ({why})")
        ends_theta: list = []
        lower, upper = profile_interval(result, name, level, ends_theta=ends_theta)
        j = result.free_names.index(name)
        value, std = result.parameters[name]["value"], result.parameters[name]["std"]
        wald, _ = wald_interval(name, value, std)
        out[name] = {"level": level, "lower": lower, "upper": upper,
                     "wald_lower": wald[0], "wald_upper": wald[1], "why": why,
                     "agrees": _agree(name, (lower, upper), wald, stds[j]),
                     "trades_with": _partners(result, j, theta_hat, ends_theta, stds)}
        per_check = (time.perf_counter() - t0) / (i + 1)
    return out


def is_log_parameter(name: str) -> bool:
    """Whether the fit moves this parameter's log (its Wald interval is then taken on the
    log scale): every positive parameter, that is all but initial temperatures and the
    signed effect parameters."""
    from ..model._spec import EFFECT_KINDS

    parts = name.split(".")
    if parts[0] == "effects" and len(parts) >= 3:
        kind = EFFECT_KINDS.get(parts[1])
        return kind is not None and parts[-1] in kind.positive
    return not name.endswith(".initial")



def wald_interval(name: str, value: float, std: float) -> tuple[tuple[float, float], str]:
    """95 % Wald interval of a parameter and its kind: value ± 1.96 std ("Wald"), or for a
    positive (log-parameterized) one exp(log value ± 1.96 std / value) ("Wald, log
    scale")."""
    if is_log_parameter(name) and value > 0:
        half = Z95 * std / value
        return (value * math.exp(-half), value * math.exp(half)), "Wald, log scale"
    return (value - Z95 * std, value + Z95 * std), "Wald"


def _agree(name: str, profile, wald, std_theta: float) -> bool:
    if None in profile:
        return False
    log = is_log_parameter(name) and min(*profile, *wald) > 0
    to_theta = math.log if log else float
    half = Z95 * std_theta
    return all(abs(to_theta(p) - to_theta(w)) <= AGREE * half for p, w in zip(profile, wald))


def _theta_stds(result: FitResult) -> np.ndarray:
    ident = result.identifiability
    if ident.stds is not None:
        return np.asarray(ident.stds, float)
    return np.sqrt(np.clip(np.diag(np.asarray(ident.covariance)), 0, None))


def _partners(result: FitResult, j: int, theta_hat, ends_theta, stds) -> list[str]:
    """The other free parameters (not initial temperatures) that moved, at either end of
    parameter `j`'s profile, by more than `MOVED_STDS` of their stds (any amount where
    undetermined) and more than `MOVED_RELATIVE`."""
    names = result.free_names
    moved = set()
    for theta in ends_theta:
        if theta is None:
            continue
        for k, name in enumerate(names):
            if k == j or name.endswith(".initial"):
                continue
            step = abs(float(theta[k] - theta_hat[k]))
            floor = math.log1p(MOVED_RELATIVE) if is_log_parameter(name) else \
                MOVED_RELATIVE * max(abs(float(theta_hat[k])), 1e-12)
            if step > floor and not step <= MOVED_STDS * float(stds[k]):  # inf: undetermined
                moved.add(name)
    return [n for n in names if n in moved]


def interval_lines(checks: dict[str, dict]) -> list[str]:
    """report.md lines: each check whose profile and Wald intervals disagree."""
    lines = []
    for name, c in checks.items():
        if c["agrees"]:
            continue
        prof = "[" + ", ".join("open" if e is None else f"{e:.4g}"
                               for e in (c["lower"], c["upper"])) + "]"
        trade = (f"; along it {', '.join(c['trades_with'])} move with it (they trade against "
                 "each other)" if c["trades_with"] else "")
        lines.append(f"- profile check of {name} ({c['why']}): the data support {prof}, "
                     f"not the Wald [{c['wald_lower']:.4g}, {c['wald_upper']:.4g}]{trade}.")
    return lines
