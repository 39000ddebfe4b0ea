"""`design`: the chamber profile that best determines a model's parameters, within the limits.

A search over the schedule's numbers (`ProfileSchedule`) from several starts, each by
L-BFGS-B (`scipy.optimize.minimize`) on the criterion's exact gradient (JAX through the
sampled inputs and the forward sensitivities, `_information`); the best end wins. The
design is then judged as the fit will judge it: each parameter's predicted std by the
fit's identifiability analysis of the same information, beside those of the reference
profiles (`_references`) of the same length.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from ..measurements._profiles import Profile
from ..model._spec import ModelSpec
from ._criterion import criterion_loss, target_indices
from ._information import (InformationProblem, information_problem, marginal_information,
                           predicted_stds)
from ._limits import ChamberLimits
from ._references import REFERENCES, prbs_start, reference_inputs
from ._schedule import ProfileSchedule

#: s, default spacing of the temperature knots (10 min).
KNOT_S = 600.0
#: s, default length of a power level (1 min: the reference PRBS's bit).
POWER_STEP_S = 60.0

#: Bound on each schedule number: σ(±8) is within 0.04 % of a limit.
_Z_BOUND = 8.0


@dataclass
class Evaluated:
    """A profile judged: its criterion value (the loss a search minimizes), predicted stds
    (relative for positive parameters; None where undetermined) and how it meets the
    limits."""

    loss: float
    stds: dict[str, float | None]
    violations: list[str] = field(default_factory=list)
    undetermined: list[str] = field(default_factory=list)  # what is not determined, and why


@dataclass
class Design:
    """A designed profile and what it is predicted to achieve.

    - `schedule`, `params`: the description and its numbers (K + M,).
    - `temperature`, `power`: the sampled profile (times,), °C and W.
    - `criterion`, `targets`: `"d"` or `"variance"` and the named parameters.
    - `designed`: the design's `Evaluated`; `references`: name -> `Evaluated`.
    - `start_losses`: the loss each start ended at, best first.
    - `noise`: sensor noise stds, °C, by column.
    - `wall_time_s`: time of the search, s.
    """

    spec: ModelSpec
    schedule: ProfileSchedule
    params: np.ndarray
    temperature: np.ndarray
    power: np.ndarray
    criterion: str
    targets: list[str]
    designed: Evaluated
    references: dict[str, Evaluated]
    start_losses: list[float]
    noise: dict[str, float]
    wall_time_s: float
    problem: InformationProblem = field(repr=False, default=None)
    n_iterations: int = 0  # L-BFGS-B iterations, all starts together
    n_evaluations: int = 0  # criterion and gradient evaluations, all starts together

    @property
    def ts(self) -> np.ndarray:
        return self.schedule.ts

    def profile(self) -> Profile:
        """The design as a `measurements.Profile`."""
        return Profile(ts=self.ts, temperature=self.temperature, power=self.power)


def design(spec: ModelSpec, duration_s: float, *, limits: ChamberLimits | None = None,
           dt: float = 1.0, criterion: str = "d", parameters: list[str] | None = None,
           n_starts: int = 4, temperature_segments: int | None = None,
           power_segments: int | None = None,
           noise: float | None = None, seed: int = 0, max_steps: int = 300,
           references: tuple[str, ...] = REFERENCES, progress=None) -> Design:
    """Design a chamber profile of `duration_s` seconds for `spec`'s free parameters.

    **Arguments:**

    - `spec`: the model, linearized at its file's values (a linear model).
    - `duration_s`: profile length, s; `dt`: sample period, s.
    - `limits`: the `ChamberLimits` (default: −40..85 °C, 10 °C/min, 0..1 W, start 25 °C).
    - `criterion`: `"d"` (D-optimal) or `"variance"` (the `parameters` named).
    - `n_starts`: searches, the first from the reference PRBS (so the design ends no
      worse than it by the criterion), the second from a still chamber at half power, the
      others from random schedules (`seed`).
    - `temperature_segments`, `power_segments`: the schedule's `K` and `M` (default one
      ramp per `KNOT_S` and one power level per `POWER_STEP_S`, at least one each; set to 0
      where the model has no boundary or no heat input).
    - `noise`: one sensor noise std for every sensor, °C (default: the model's).
    - `max_steps`: L-BFGS-B iterations per start.

    **Returns:** a `Design`.
    """
    say = progress or (lambda *a, **k: None)
    limits = limits or ChamberLimits()
    n_periods = max(int(round(duration_s / dt)), 1)
    if temperature_segments is None:
        temperature_segments = min(max(int(round(duration_s / KNOT_S)), 1), n_periods)
    if power_segments is None:
        power_segments = min(max(int(round(duration_s / POWER_STEP_S)), 1), n_periods)
    K = temperature_segments if spec.boundary_columns else 0
    M = power_segments if spec.heat_columns else 0
    schedule = ProfileSchedule(float(duration_s), float(dt), limits, K, M)
    t0 = time.perf_counter()
    say("linearizing the model over the profile's samples (compiles the sensitivities)")
    problem = information_problem(spec, schedule.ts, limits.start_c, limits.start_power_w,
                                  noise)
    judged = problem.judged
    targets = target_indices(judged, parameters, criterion, spec.source)

    def loss_of_inputs(u):
        Fm = marginal_information(problem.information(u), problem.nuisance)
        return criterion_loss(Fm, criterion, targets)

    def loss(z):
        return loss_of_inputs(problem.inputs(*schedule.sampled(z)))

    value_and_grad = jax.jit(jax.value_and_grad(loss))

    def fun(z):
        v, g = value_and_grad(jnp.asarray(z))
        v, g = float(v), np.asarray(g, float)
        if not np.isfinite(v):  # a schedule where the criterion breaks down: a wall
            return 1e300, np.zeros_like(g)
        return v, g

    rng = np.random.default_rng(seed)
    n = schedule.n_parameters
    starts = ([prbs_start(schedule)] if M else []) + [np.zeros(n)]
    starts = (starts + [rng.normal(0.0, 2.0, n) for _ in range(max(n_starts, 1))]
              )[:max(n_starts, 1)]
    ends, n_it, n_ev = [], 0, 0
    for i, z0 in enumerate(starts):
        say(f"search {i + 1}/{len(starts)} over {n} schedule numbers")
        if n == 0:
            ends.append((fun(z0)[0], z0))
            continue
        res = scipy.optimize.minimize(fun, z0, jac=True, method="L-BFGS-B",
                                      bounds=[(-_Z_BOUND, _Z_BOUND)] * n,
                                      options={"maxiter": max_steps})
        ends.append((float(res.fun), np.asarray(res.x)))
        n_it, n_ev = n_it + int(res.nit), n_ev + int(res.nfev)
    ends.sort(key=lambda e: e[0])
    best_loss, best = ends[0]
    wall = time.perf_counter() - t0
    T, P = (np.asarray(a) for a in schedule.sampled(jnp.asarray(best)))

    judge = jax.jit(lambda u: problem.information(u))

    def evaluate(T, P) -> Evaluated:
        u = problem.inputs(jnp.asarray(T), jnp.asarray(P))
        F = np.asarray(judge(u))
        value = float(loss_of_inputs(u))
        stds, why = predicted_stds(F, problem)
        return Evaluated(value, stds, limits.violations(schedule.ts, T, P), why)

    designed = evaluate(T, P)
    refs = {}
    for name in references:
        rT, rP = reference_inputs(name, schedule, spec)
        refs[name] = _evaluate_reference(spec, schedule, rT, rP, noise, criterion, targets)
    noise_by_column = dict(zip(problem.spec.sensor_columns, problem.sigma.tolist()))
    return Design(spec, schedule, best, T, P, criterion,
                  [judged[i] for i in targets] if targets is not None else [], designed, refs,
                  [e[0] for e in ends], noise_by_column, wall, problem, n_it, n_ev)


def _evaluate_reference(spec, schedule, T, P, noise, criterion, targets) -> Evaluated:
    """A reference judged by its own linearization (its own start: the unit at rest at
    its first sample)."""
    prob = information_problem(spec, schedule.ts, float(T[0]), float(P[0]), noise)
    u = prob.inputs(jnp.asarray(T), jnp.asarray(P))
    F = jax.jit(prob.information)(u)
    loss = criterion_loss(marginal_information(F, prob.nuisance), criterion, targets)
    stds, why = predicted_stds(np.asarray(F), prob)
    return Evaluated(float(loss), stds, schedule.limits.violations(schedule.ts, T, P), why)
