"""Refitting a candidate: the model extended by its effect, fitted from several starts
(`_refit_starts`), every start of every candidate side by side (`_refit_side_by_side`,
`_fit_plans`), once more from the nested model's optimum where every start failed or
ended below it (`_needs_retry`), and concluded from the best start (`_refit`); the
best-scored candidates refitted in waves (`refit_best`)."""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import numpy as np

from ._candidates import Candidate, new_effect
from ._refit_verdicts import (absorbing_nodes, added_effect, duplicate_reason, rule_p_value,
                              sample_period)
from ._step import Step, evaluate
from ..fitting._side_by_side import side_by_side
from ..measurements._telemetry import Telemetry
from ..model._parameters_by_name import spec_parameters, with_spec_parameters
from ..model._spec import EFFECT_KINDS, ModelSpec
from ..model.effects import KINDS
from ..model.effects._base import T_REF


MIN_FACTOR = 0.25  # a refit's start keeps every G(T), C(T), G(u) above this share of G0, C0


def _within_data(c: Candidate, leading: float | None, runs: list[Telemetry],
                 spec: ModelSpec) -> float | None:
    """The score test's estimate of a temperature or input coefficient, clipped so that the
    factor it scales, `1 + a x` (x: T − 25 °C over the recorded temperatures, or the input
    column), stays at least `MIN_FACTOR` over the data: a one-step estimate can overshoot
    to a negative conductance or capacitance, whose model cannot even be simulated."""
    if leading is None or not np.isfinite(leading) or c.kind not in (
            "conductance_temperature", "capacitance_temperature", "conductance_input"):
        return leading
    if c.kind == "conductance_input":
        xs = np.concatenate([t.column(c.where[2]) for t in runs])
    else:
        cols = [*spec.sensor_columns, *spec.boundary_columns]
        xs = np.concatenate([t.column(k) for t in runs for k in cols]) - T_REF
    xs = xs[np.isfinite(xs)]
    if xs.size == 0:
        return leading
    lo, hi = float(xs.min()), float(xs.max())
    room = 1.0 - MIN_FACTOR
    if leading > 0 and lo < 0:
        return min(leading, room / -lo)
    if leading < 0 and hi > 0:
        return max(leading, -room / hi)
    return leading


def _candidate_effect(c: Candidate, spec, lowered, holds: dict, leading=None,
                      time_constant=None):
    """The effect to add for `c`: a kind's first guess, or a learned law with its
    coefficient at `leading` (the score test's estimate; else zero) and its best shape."""
    if c.learned is not None:
        hold = next((holds[w] for w in c.columns() if w in holds), None)
        c0 = leading if leading is not None and np.isfinite(leading) else 0.0
        return c.learned.effect(c.where, c0, c.shape, hold)
    return new_effect(spec, lowered, c.kind, c.where, holds, leading, time_constant)


def _at_null(effect):
    """`effect` with its leading parameter at the null (zero, or a thousandth of its first
    guess for a positive one) and an added mass's process noise a thousandth of its start:
    the extended model then predicts as the nested one."""
    from ..model._spec import Parameter

    lead = "c" if effect.kind == "expression" else EFFECT_KINDS[effect.kind].parameters[0]
    value = effect.parameters[lead].value
    value = 1e-3 * value if lead in EFFECT_KINDS[effect.kind].positive else 0.0
    params = {**effect.parameters, lead: Parameter(float(value))}
    if "process_noise" in params:  # an added mass's own diffusion, near zero too
        params["process_noise"] = Parameter(1e-3 * params["process_noise"].value)
    return dataclasses.replace(effect, parameters=params)


START_FITTED = "the fitted model with the effect's first guess"
START_USER = "the user's values with the effect's first guess"
START_NESTED = "the nested model's optimum with the effect at zero"
START_TAU = "the fitted model with the effect at the score test's best time constant"
TAU_START_RATIO = 3.0  # a time-constant start is added when it is this far from the guess


def _far_from(effect, other) -> bool:
    """Whether some parameter of `effect` is over `TAU_START_RATIO` times from `other`'s."""
    return any(not (1 / TAU_START_RATIO < p.value / other.parameters[k].value <
                    TAU_START_RATIO) for k, p in effect.parameters.items()
               if other.parameters[k].value > 0)


def _refit_starts(c: Candidate, step: Step, new_columns, initial, runs=(), nested=False
                  ) -> list[tuple]:
    """`(hold, start, model)` for each fit that refitting the model of `step` with candidate
    `c` takes: from the fitted model plus the effect's first guess and, with `initial`,
    also from the user's values (a learned law from the user's values alone: see
    below); for a mass or a lag whose best score direction's time
    constant is over `TAU_START_RATIO` from the first guess's, also from the fitted model
    with the effect at that time constant; with `nested`, only from the fitted model with the effect
    at its null (`_at_null`: the retry of a refit that failed or ended below the nested
    model). An effect that brings a data column into the model (one of `new_columns`) is
    tried with the column held each way, "zoh" and "foh" (`_refit`).

    A learned law's refit, a nonlinear model whose shape is free, is a step's costliest
    fit (under the Kalman likelihood 10-40 s a start on PRBS1, against 1-13 s for a
    kind's), and the fitted model is the start where it does worst: that model has bent
    its parameters to mimic what it lacks (docs/extensions.md), and on PRBS1 the law from
    there ended at a likelihood ratio of 50.5 and 4.0 (steps 2 and 3) where from the
    user's values it reached 60.3 and 48.4. So a law starts from the user's values
    alone where they are given; a failed start is retried from the nested model's
    optimum like any other (`_needs_retry`)."""
    spec, lowered = step.spec, step.result.lowered_spec
    brings = [w for w in c.columns() if w in new_columns]
    diffusing = _with_process_noise(c, step)
    # A nonlinear effect starts at the score test's estimate (clipped to the data), not at
    # its null value: the fit chooses how finely to integrate it (`fitting._integration`).
    leading = _within_data(c, c.estimate, runs, spec) if KINDS[c.kind].nonlinear else None
    starts = []
    # a refined law replaces the laws it refines (`_symbolic_step.refine_laws`)
    kept = tuple(e for i, e in enumerate(spec.effects) if i not in c.replaces)
    for hold in ("zoh", "foh") if brings else (None,):
        try:
            effect = diffusing(_candidate_effect(c, spec, lowered, {w: hold for w in brings},
                                                 None if nested else leading))
            if nested:
                starts.append((hold, START_NESTED,
                               spec.replace(effects=kept + (_at_null(effect),))))
                continue
            extended = spec.replace(effects=kept + (effect,))
            if initial is None or c.learned is None:
                starts.append((hold, START_FITTED, extended))
            if initial is not None:
                starts.append((hold, START_USER, with_spec_parameters(
                    extended, spec_parameters(initial))))
            if c.time_constant is not None:  # a mass or lag: also at the score's τ
                timed = diffusing(_candidate_effect(c, spec, lowered,
                                                    {w: hold for w in brings}, None,
                                                    c.time_constant))
                if _far_from(timed, effect):
                    starts.append((hold, START_TAU, spec.replace(effects=kept + (timed,))))
        except Exception as err:
            c.note = f"refit failed: {type(err).__name__}: {err}"[:300]
    return starts


def _with_process_noise(c: Candidate, step: Step):
    """`f(effect)`: under the Kalman likelihood, an added mass gets a process noise of its
    own to estimate, starting at the median of the model's free ones (every state of a
    CTSM-R building model has one; without it the PRBS1 envelope and heater cannot carry
    the weather's unmodelled heat); otherwise the effect unchanged."""
    from ..model._spec import Parameter

    free = [p["value"] for name, p in step.record["parameters"].items()
            if name.endswith(".process_noise") and p.get("free") and p["value"] > 0]
    if c.kind != "extra_node" or step.result.likelihood != "kalman" or not free:
        return lambda effect: effect
    q = float(np.median(free))
    return lambda effect: dataclasses.replace(
        effect, parameters={**effect.parameters, "process_noise": Parameter(q)})


def _needs_retry(fits: list[tuple], step: Step) -> bool:
    """Whether every start of a refit failed or ended below the nested model (a nested
    refit that ends worse than the model without the effect did not reach its optimum)."""
    nlls = [got.record["nll"] for _, _, got in fits if not isinstance(got, Exception)]
    return not nlls or min(nlls) > step.record["nll"] + NESTED_TOL


# −log L a refit may end above its nested model and still be at it: the solvers stop
# when a step would gain less than about this (an absent effect's refit ends at the null)
NESTED_TOL = 1e-3


def _refit(c: Candidate, step: Step, runs, new_columns, fits: list[tuple], say,
           white_p: float = 0.01) -> bool:
    """Complete candidate `c` from its refits `fits`, `(hold, start, Step or the exception
    the fit raised)` for each of `_refit_starts`: on success `c` holds the likelihood
    ratio, its p-value, Δ BIC, the extended step, the fitted parameters and which start
    won (`c.refit_start`).

    The better likelihood of the starts is kept; an effect that brings a data column
    into the model keeps the hold of the better likelihood (`c.hold`; the other's
    likelihood ratio goes into the note). A refit that still ends below the nested model
    has not found the extended model's optimum, which is at least the nested one's (the
    effect at its null): its likelihood ratio is reported as 0 and it is not supported."""
    by_hold, ext = {}, None
    c.refit_seconds = sum(got.fit_seconds for _, _, got in fits
                          if not isinstance(got, Exception))
    c.refit_fits = len(fits)
    for hold, start, got in fits:
        if isinstance(got, Exception):  # one candidate's failure must not end the loop
            c.note = f"refit from {start} failed: {type(got).__name__}: {got}"[:300]
            continue
        if hold not in by_hold or got.record["nll"] < by_hold[hold][1].record["nll"]:
            by_hold[hold] = (start, got)
    brings = [w for w in c.columns() if w in new_columns]
    for hold, (start, got) in by_hold.items():
        if ext is None or got.record["nll"] < ext.record["nll"]:
            ext, c.hold, c.refit_start = got, hold, start
    if ext is None:
        c.supported = False
        return False
    ext.starts = sum(h == c.hold and not isinstance(got, Exception) for h, _, got in fits)
    failed = [f"{start} ({type(got).__name__}: {str(got)[:120]})"
              for _, start, got in fits if isinstance(got, Exception)]
    c.note = (f"refit from {', '.join(failed)} failed; from {c.refit_start} it succeeded"
              if failed else "")
    if len(by_hold) == 2:
        other = next(h for h in by_hold if h != c.hold)
        lr_other = 2 * (by_hold[other][1].record["nll"] - ext.record["nll"])
        c.add_note(f"{', '.join(brings)} held as {c.hold!r}: its likelihood ratio over "
                   f"{other!r} is {lr_other:.1f}")
        say(c.note)
    lr = 2 * (step.record["nll"] - ext.record["nll"])
    c.result = ext
    added = added_effect(ext.spec, c)
    c.parameters = {k: p.value for k, p in added.parameters.items()}
    first = KINDS[c.kind].initial_parameters(step.result.lowered_spec, c.where)
    c.duplicate = duplicate_reason(c, first, sample_period(runs))
    if c.duplicate:
        say(c.duplicate)
    if lr < 0 and (lr >= -2 * NESTED_TOL or c.duplicate):
        # At the nested optimum to the solver's tolerance, or run to the effect's own
        # boundary (a mass or lag far faster than a sample, a positive parameter at zero:
        # the null, which a log parameter reaches only in the limit): the effect is absent.
        lr = 0.0
    if lr < 0:
        c.add_note(
            f"every refit ended below the nested model (−log L {-lr / 2:.3g} higher): the "
            "extended model's optimum was not found, and it is at least the nested one's "
            "(the effect at zero), so the likelihood ratio is reported as 0")
        lr = 0.0
    n_new = ext.record["n_params"] - step.record["n_params"]
    c.score, c.method = float(lr), "refit"
    c.lr_deflation = ext.deflation(white_p)
    c.p_value = rule_p_value(c.kind, lr / c.lr_deflation, n_new, runs)
    c.delta_bic = -lr + n_new * math.log(step.record["n_samples"]) if lr == 0.0 else \
        ext.record["bic"] - step.record["bic"]
    c.absorbed_by = absorbing_nodes(step, ext)
    if c.absorbed_by:
        moved = "; ".join(f"{n} ({', '.join(ps)})" for n, ps in c.absorbed_by.items())
        c.add_note(f"near-tie with the unmeasured node {moved}: its parameters moved to "
                   f"mimic the effect when it was absent; a sensor on "
                   f"{' or '.join(c.absorbed_by)} would separate them")
    return True


def refittable(cands: list[Candidate]) -> list[Candidate]:
    """The candidates of `cands` a refit may take: score-tested and scored above zero."""
    return [c for c in cands if c.method == "score" and c.score > 0]


def refit_best(cands: list[Candidate], refits: int, refit_wave,
               beside: list[Candidate] = ()) -> None:
    """Refit the best-scored thermal candidates (`cands` in decreasing score) until
    `refits` succeeded or `2 refits` were tried (a failure counts half), in waves:
    `refit_wave(list) -> list[bool]` refits each wave's candidates (side by side), a
    wave as many as are still wanted, so exactly the candidates that refitting one at a
    time would try are tried. The `beside` candidates (score-tested, scored above zero)
    are refitted whatever their rank, first in the first wave: they fill the cores while
    the ranked candidates fit, and their outcome does not count."""
    pending = refittable(cands)
    extra = [c for c in refittable(beside) if c not in pending]
    done = tried = 0
    while extra or (pending and done < refits and tried < 2 * refits):
        size = min(refits - done, 2 * refits - tried) if pending else 0
        wave, pending = pending[:size], pending[size:]
        tried += len(wave)
        done += sum(refit_wave(extra + wave)[len(extra):])
        extra = []


def _refit_side_by_side(cands: list[Candidate], step: Step, runs, likelihood, new_columns,
                        initial, say, white_p: float = 0.01) -> list[bool]:
    """`_refit` each candidate, every fit of every candidate side by side
    (`fitting._side_by_side`: the answers are those of fitting one at a time, whatever
    the threads). Each candidate's first start is fitted before any second start, so
    that fits of one model structure seldom wait for each other's compilation. A
    candidate whose every start failed or ended below the nested model is refitted once
    more from the nested model's optimum with the effect at zero (`_needs_retry`). A
    learned law's refit is not polished (`fit`'s `polish`): its coefficient and shape
    move together, and the polish's walk along that valley, 0.4-1.2 in −log L on
    PRBS1, cost it 16 s a step (docs/extensions.md)."""
    plans = []
    for c in cands:
        say(f"refitting with {c.kind} {list(c.where)} (score {c.score:.1f})")
        plans.append(_refit_starts(c, step, new_columns, initial, runs))
    polish = [c.learned is None for c in cands]
    fits = _fit_plans(plans, runs, likelihood, step.thermal_nll, polish)
    retry = [i for i, f in enumerate(fits) if _needs_retry(f, step)]
    for i in retry:
        say(f"refitting {cands[i].kind} {list(cands[i].where)} again from {START_NESTED}")
    more = _fit_plans([_refit_starts(cands[i], step, new_columns, initial, runs, nested=True)
                       for i in retry], runs, likelihood, step.thermal_nll,
                      [polish[i] for i in retry])
    for i, m in zip(retry, more):
        fits[i] = fits[i] + m
    return [_refit(c, step, runs, new_columns, fits[i], say, white_p)
            for i, c in enumerate(cands)]


def _fit_plans(plans: list[list[tuple]], runs, likelihood, nested_nll: float,
               polish: list[bool]) -> list[list[tuple]]:
    """Every `(hold, start, model)` of every plan, each a model that extends one with
    −log L `nested_nll`, fitted side by side (polished as `polish` says per plan, `fit`'s):
    first starts first, then the later starts of the plans with the most starts (so that
    a wave seldom ends on one plan's last start alone): per plan, `(hold, start, Step or
    the exception its fit raised)`.

    Only a hold's first start, when its Kalman fit does not converge, is fitted again
    from the output-error fit (`fit`'s `restart_unconverged`): a later start is one
    more start, not the candidate's only chance. On PRBS1 no later start's restart
    won (the heater mass's τ start at step 3: 15 s, on the step's critical path, to end
    0.026 above its first start)."""
    order = sorted(((k, i) for i, plan in enumerate(plans) for k in range(len(plan))),
                   key=lambda ki: (0, ki[1], 0) if ki[0] == 0 else
                   (1, -len(plans[ki[1]]), ki[1], ki[0]))

    def evaluated(model, polish, first):  # a Step, or the exception `_refit` reports
        t0 = time.perf_counter()
        try:
            got = evaluate(model, runs, likelihood, nested_nll=nested_nll, polish=polish,
                           restart_unconverged=first)
        except Exception as err:
            return err
        if isinstance(got, Step):
            got.fit_seconds = time.perf_counter() - t0
        return got

    def first(plan, k):
        return k == 0 or plan[k][0] != plan[k - 1][0]

    done = dict(zip(order, side_by_side([functools.partial(evaluated, plans[i][k][2],
                                                           polish[i], first(plans[i], k))
                                         for k, i in order])))
    return [[(hold, start, done[k, i]) for k, (hold, start, _) in enumerate(plan)]
            for i, plan in enumerate(plans)]
