"""The missing-physics loop (`thermojax investigate`, docs/formats.md §5).

Fit the model; if its residuals are not white, score every candidate effect
(`_candidates`), refit the best few, and add the best one the evidence supports;
repeat until the residuals are white, no candidate is supported, or `max_steps`.

A candidate is *supported* by the selection rule of `_selection` (stated there once,
used by `diagnose` too): forward selection by likelihood-ratio tests (Benjamini-Hochberg,
a BIC drop of `MIN_BIC_DROP`), then a held-out check whose broken folds do not vote.

Every fit inside the loop fails softly: a candidate whose refits all raise or go
non-finite is reported with the reason and never supported; a held-out fit that fails
makes its fold inconclusive.

Candidates whose likelihood ratios differ by less than the 95 % point of χ²₁ (3.84)
are reported as tied (`tied_with`): the data cannot tell them apart.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from scipy import stats

import dataclasses

from ..fitting._bias import fit_bias, viscoelastic_candidate
from ._candidates import (Candidate, column_role, enumerate_places, helper_nodes,
                          new_effect, refit_p_value, score_candidates)
from ..measurements._data import Experiment
from ..fitting._fit import FitResult, fit, output_error_at, standardized_innovations
from ..fitting._side_by_side import side_by_side
from ..fitting._solver import TruncatedGaussNewton
from .._blas_threads import one_blas_thread
from .._errors import InputError
from .._json import json_safe
from .._memory import release_compiled_if_crowded
from ..model._model_file import dump_model, save_model
from ..model._parameters_by_name import spec_parameters, with_spec_parameters
from .._residual_analysis import ljung_box, long_run_variance_ratio
from ._diagnostics import davies_p_value, davies_variation
from ._physical_range import data_span, prefer_physics, reject_unphysical
from ._selection import (FoldVote, fold_vote, held_out_advice, holdout_verdict, judge,
                         prefer_vocabulary, significance_rule)
from ..discovery import column_scales, learned_places
from ..model._spec import EFFECT_KINDS, ModelSpec
from ..model.effects import KINDS
from ..model.effects._base import T_REF
from ..measurements._telemetry import Telemetry
from ._plots_ahead import PlotsAhead

N_BLOCKS = 4  # held-out folds when there are fewer than three runs
N_STARTS = 3  # output-error starts confirming each step's optimum before it is scored
MULTISTART_TOL = 1e-3  # −log L a perturbed start must gain to replace the fit
DAVIES_KINDS = ("extra_node", "viscoelastic")  # a time constant absent under the null
VISCOELASTIC_TAU_RANGE = (1.0, 1e5)  # s, the τ search of `viscoelastic_candidate`


@dataclass
class Step:
    """One fitted model of the loop and its evidence."""

    spec: ModelSpec
    result: FitResult
    biases: dict  # column -> BiasFit
    record: dict  # the step's report.json entry
    traces: list[dict] = field(repr=False, default_factory=list)
    lrv: dict = field(default_factory=dict)  # column -> long-run variance ratio of residuals
    starts: int = 1  # how many fits from distinct starts `result` is the best of
    # `(likelihood, Future)` of `scoring_inputs`, computed ahead (`score_ahead`)
    scoring: tuple | None = field(default=None, repr=False)

    def deflation(self, white_p: float) -> float:
        """The long-run variance ratio that deflates statistics: the largest over the
        columns whose residuals are not white at `white_p` (1 when all are white)."""
        bad = [c for c, p in self.record["whiteness_p"].items()
               if p is None or not p > white_p]
        return float(max([self.lrv.get(c, 1.0) for c in bad], default=1.0))

    @property
    def thermal_nll(self) -> float:
        """−log L of the thermal model alone: a Kalman fit's record adds its bias
        channels' (`fitting._summary`)."""
        kalman = self.result.likelihood == "kalman"
        return self.record["nll"] - (sum(b.nll for b in self.biases.values()) if kalman
                                     else 0.0)


# ---------------------------------------------------------------------------
# Evaluating one model


def _experiments(spec: ModelSpec, runs: list[Telemetry]) -> list[Experiment]:
    return [Experiment.from_telemetry(spec, t, name=t.path or f"run{i}")
            for i, t in enumerate(runs)]


def _bias_runs(result, runs, bias):
    """`(runs, node rates)` for `fitting._bias` on the fitted model's free-run node
    temperatures: per run `(ts, node temperatures, bias column)` and the exact `dT/dt`."""
    from ..fitting._bias_residuals import node_temperatures

    x, xdot = (np.asarray(a) for a in node_temperatures(
        result.model, result.problem.data, result.state.run_initial))
    return ([(np.asarray(t.ts), x[r, :len(t.ts)], t.column(bias.column))
             for r, t in enumerate(runs)], [xdot[r, :len(t.ts)] for r, t in enumerate(runs)])


def evaluate(spec: ModelSpec, runs: list[Telemetry], likelihood: str, progress=None,
             holdout: int | None = None, n_starts: int = 1,
             nested_nll: float | None = None, polish: bool = True,
             restart_unconverged: bool = True) -> Step:
    """Fit `spec` to the runs, its bias channels with it (docs/formats.md §4), and measure
    the fit (docs/formats.md §5 keys). `n_starts` > 1 adds perturbed output-error starts;
    `nested_nll`: −log L of the model `spec` extends; `polish` and `restart_unconverged`
    as `fit`'s."""
    # Plateau restarts (`fitting._plateau`) stay with `fit`: here a candidate's node
    # beyond the data is evidence against it, and each step's fit is compared as it is.
    result = fit(spec, _experiments(spec, runs), likelihood=likelihood, progress=progress,
                 holdout=holdout, n_starts=n_starts, restart_plateaus=False,
                 nested_nll=nested_nll, polish=polish,
                 restart_unconverged=restart_unconverged)
    biases = result.biases
    spec_out = result.spec
    nll, n_params, n = result.nll, result.n_params, result.n_samples
    rmse = dict(result.rmse)
    # whiteness: free-run residuals (output error) or standardized innovations (Kalman)
    cols = list(spec.sensor_columns)
    if likelihood == "kalman":
        seq = standardized_innovations(result)
    else:
        exps = _experiments(spec, runs)
        seq = [e.outputs - p for e, p in zip(exps, result.predictions)]
    tests = {c: ljung_box([s[:, j] for s in seq]) for j, c in enumerate(cols)}
    tests.update({c: ljung_box(f.residuals) for c, f in biases.items()})
    white = {c: p for c, (_, p, _) in tests.items()}
    lags = {c: lag for c, (_, _, lag) in tests.items()}
    params = dict(result.parameters)
    record = {
        "added": None, "n_params": int(n_params), "rmse": rmse,
        "nll": float(nll), "aic": float(2 * n_params + 2 * nll),
        "bic": float(n_params * math.log(n) + 2 * nll),
        "whiteness_p": white, "whiteness_lags": lags, "candidates": [],
        "fit_percent": dict(result.fit_percent), "n_samples": int(n),
        "parameters": params, "converged": bool(result.converged),
    }
    if not (np.isfinite(record["nll"]) and np.isfinite(record["bic"])):
        raise FloatingPointError(f"the fit's −log L is not finite ({record['nll']})")
    # Deflation for autocorrelated residuals (`Step.deflation`): free-run residuals only.
    # The Kalman likelihood's innovations are whitened by the model itself, and its
    # likelihood-ratio test is used as the field uses it (Bacher & Madsen; CTSM-R): on
    # PRBS1 a deflation of 4 (the innovations of an incomplete model) hid the solar gain
    # on the envelope (LR 34) that the paper's selection keeps.
    lrv = {c: 1.0 if likelihood == "kalman" else
           long_run_variance_ratio([s[:, j] for s in seq]) for j, c in enumerate(cols)}
    lrv.update({c: long_run_variance_ratio(f.residuals) for c, f in biases.items()})
    step = Step(spec_out, result, biases, record, lrv=lrv)
    step.traces = _traces(spec, runs, result, biases)
    return step


def _traces(spec, runs, result, biases) -> list[dict]:
    """Measured and modelled columns per run, for plots (`_diagnostics.RunTrace`)."""
    out = []
    cols = list(spec.sensor_columns)
    inputs = list(spec.input_columns)
    for r, t in enumerate(runs):
        meas = [t.column(c) for c in cols] + [t.column(c) for c in biases]
        pred = [result.predictions[r][:, j] for j in range(len(cols))] + \
               [biases[c].predictions[r] for c in biases]
        out.append({"name": t.path or f"run{r}", "ts": np.asarray(t.ts),
                    "measured": np.stack(meas, 1), "predicted": np.stack(pred, 1),
                    "inputs": np.stack([t.column(c) for c in inputs], 1) if inputs
                    else np.zeros((len(t.ts), 0))})
    return out


# ---------------------------------------------------------------------------
# One step of diagnosis


def unused_columns(spec: ModelSpec, runs: list[Telemetry]) -> dict[str, str]:
    """Data columns every run holds that the model does not use, with a role guess."""
    used = set(spec.input_columns) | set(spec.sensor_columns) | {b.column for b in spec.biases}
    common = set(runs[0].names)
    for t in runs[1:]:
        common &= set(t.names)
    out = {}
    for c in runs[0].names:
        if c in common and c not in used and c != "time_s":
            values = np.concatenate([t.column(c) for t in runs])
            if np.all(np.isfinite(values)):
                out[c] = column_role(c, values)
    return out


def _padded_columns(runs: list[Telemetry], names, T: int) -> dict[str, np.ndarray]:
    """Data columns `names` as (runs, T) arrays on the padded time grid (each run's last
    value repeated)."""
    columns = {}
    for c in names:
        arr = np.zeros((len(runs), T))
        for i, t in enumerate(runs):
            v = t.column(c)
            arr[i, :len(v)] = v
            arr[i, len(v):] = v[-1]
        columns[c] = arr
    return columns


def rule_p_value(kind: str, lr: float, n_new: int, runs: list[Telemetry]) -> float:
    """p-value of a (deflated) likelihood-ratio statistic: Davies' bound for the kinds
    whose time constant does not exist under the null, else `refit_p_value`."""
    if kind not in DAVIES_KINDS:
        return refit_p_value(kind, lr, max(n_new, 1))
    if kind == "viscoelastic":
        lo, hi = VISCOELASTIC_TAU_RANGE
    else:  # an extra node's local time constant: from the sample period to the record
        lo = sample_period(runs)
        hi = sum(float(t.ts[-1] - t.ts[0]) for t in runs)
    return davies_p_value(lr, max(n_new - 1, 1), davies_variation(math.log(max(hi / lo, 1.0))))


def _viscoelastic_candidates(step: Step, runs: list[Telemetry], places,
                             white_p: float = 0.01) -> list[Candidate]:
    """Every `viscoelastic` place of `places`, refitted directly on its bias channel
    (linear least squares and a τ search: cheap). A failed fit is reported, not raised."""
    spec, result = step.spec, step.result
    node_names = list(result.lowered_spec.node_names)
    n = step.record["n_samples"]
    out = []
    for kind, where in places:
        if kind != "viscoelastic":
            continue
        try:
            bias = next(b for b in spec.biases if b.column == where[1])
            bias_runs, rates = _bias_runs(result, runs, bias)
            bias_fit, lr = viscoelastic_candidate(bias, list(spec.effects), bias_runs,
                                                  node_names, where[0], node_rates=rates)
            name = f"viscoelastic.{where[0]}"
            k = float(dict(zip(bias_fit.names, bias_fit.coefficients))[f"{name}.k"])
            if not (np.isfinite(lr) and np.isfinite(k)):
                raise FloatingPointError(f"non-finite fit (LR {lr}, k {k})")
        except Exception as err:  # one candidate's failure must not end the loop
            out.append(Candidate(kind, tuple(where), float("nan"), 1.0, method="score",
                                 note=f"refit failed: {type(err).__name__}: {err}"[:300]))
            continue
        _, white, _ = ljung_box(bias_fit.residuals)
        d = long_run_variance_ratio(bias_fit.residuals) if not white > white_p else 1.0
        c = Candidate(kind, tuple(where), float(lr), rule_p_value(kind, lr / d, 2, runs),
                      method="refit", delta_bic=-lr + 2 * math.log(n), lr_deflation=d,
                      parameters={"time_constant": bias_fit.time_constants[name][0], "k": k})
        c.duplicate = duplicate_reason(c, {}, sample_period(runs))
        out.append(c)
    return out


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


def added_effect(spec: ModelSpec, c: Candidate):
    """The effect candidate `c` added to `spec` (the last of its kind at its place: a
    learned law may join another expression there)."""
    return [e for e in spec.effects if (e.kind, tuple(e.where)) == c.key][-1]


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
    for hold in ("zoh", "foh") if brings else (None,):
        try:
            effect = diffusing(_candidate_effect(c, spec, lowered, {w: hold for w in brings},
                                                 None if nested else leading))
            if nested:
                starts.append((hold, START_NESTED,
                               spec.replace(effects=spec.effects + (_at_null(effect),))))
                continue
            extended = spec.replace(effects=spec.effects + (effect,))
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
                    starts.append((hold, START_TAU,
                                   spec.replace(effects=spec.effects + (timed,))))
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


def refit_best(cands: list[Candidate], refits: int, refit_wave,
               beside: list[Candidate] = ()) -> None:
    """Refit the best-scored thermal candidates (`cands` in decreasing score) until
    `refits` succeeded or `2 refits` were tried (a failure counts half), in waves:
    `refit_wave(list) -> list[bool]` refits each wave's candidates (side by side), a
    wave as many as are still wanted, so exactly the candidates that refitting one at a
    time would try are tried. The `beside` candidates (score-tested, scored above zero)
    are refitted whatever their rank, first in the first wave: they fill the cores while
    the ranked candidates fit, and their outcome does not count."""
    pending = [c for c in cands if c.method == "score" and c.score > 0]
    extra = [c for c in beside if c.method == "score" and c.score > 0 and c not in pending]
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
        try:
            return evaluate(model, runs, likelihood, nested_nll=nested_nll, polish=polish,
                            restart_unconverged=first)
        except Exception as err:
            return err

    def first(plan, k):
        return k == 0 or plan[k][0] != plan[k - 1][0]

    done = dict(zip(order, side_by_side([functools.partial(evaluated, plans[i][k][2],
                                                           polish[i], first(plans[i], k))
                                         for k, i in order])))
    return [[(hold, start, done[k, i]) for k, (hold, start, _) in enumerate(plan)]
            for i, plan in enumerate(plans)]


FAST_FRACTION = 0.2  # a mass or lag faster than this share of a sample period is unseen
MIN_RELAXATION_SAMPLES = 3.0  # a viscoelastic τ under this many samples is white noise
AT_BOUND = 1e-6  # a positive parameter below this share of its first guess sits at zero


def sample_period(runs: list[Telemetry]) -> float:
    """The shortest of the runs' median sample periods (s)."""
    return min(float(np.median(np.diff(t.ts))) for t in runs)


def duplicate_reason(c: Candidate, first_guess: dict, period: float) -> str:
    """Why the refitted effect of `c` (its `parameters`) only duplicates structure the
    model already has, or "" when it does not: an added mass or sensor lag whose time
    constant is far below the sample `period` (s), a viscoelastic τ below a few samples,
    or a positive parameter at its bound (zero) relative to its `first_guess`."""
    p = c.parameters or {}
    if c.kind == "extra_node" and c.result is not None:
        lowered = c.result.result.lowered_spec
        new = added_effect(c.result.spec, c).name
        g = sum(k.conductance.value for k in lowered.links if new in k.between) + sum(
            b.conductance.value for b in lowered.boundaries if b.node == new)
        tau = p["capacitance"] / g if g > 0 else math.inf
        if tau < FAST_FRACTION * period:
            return (f"duplicate: the added mass's local time constant, {tau:.3g} s, is far "
                    f"below the sample period ({period:g} s), so it only splits an existing "
                    "conductance")
    if c.kind == "sensor_lag" and p.get("time_constant", math.inf) < FAST_FRACTION * period:
        return (f"duplicate: a lag of {p['time_constant']:.3g} s is far below the sample "
                f"period ({period:g} s)")
    if c.kind == "viscoelastic" and p.get("time_constant", math.inf) < \
            MIN_RELAXATION_SAMPLES * period:
        return (f"duplicate: a relaxation time of {p['time_constant']:.3g} s is below "
                f"{MIN_RELAXATION_SAMPLES:g} samples ({period:g} s each): it follows the "
                "temperature like the static terms")
    for name in EFFECT_KINDS[c.kind].positive:
        guess = first_guess.get(name)
        if name in p and guess and p[name] < AT_BOUND * guess:
            return f"duplicate: {name} went to its bound (zero): the effect is absent"
    return ""


ABSORB_STDS = 3.0  # a shift beyond this many stds (and `ABSORB_SHARE`) is mimicry
ABSORB_SHARE = 0.1


def absorbing_nodes(step: Step, extended: Step) -> dict[str, list[str]]:
    """Unmeasured nodes of `step` whose own parameters (capacitance, the conductances
    touching them) moved when the candidate's effect was added, by more than
    `ABSORB_STDS` of their std and `ABSORB_SHARE` of their value: node -> parameters.
    Without the effect those parameters were bent to mimic it, so the node and the
    effect partly stand in for each other."""
    spec = step.spec
    measured = {s.node for s in spec.sensors}
    before, after = step.record["parameters"], extended.record["parameters"]
    out: dict[str, list[str]] = {}
    for node in spec.node_names:
        if node in measured:
            continue
        for name, p in before.items():
            group, _, rest = name.partition(".")
            key = rest.rpartition(".")[0]
            touches = (group == "nodes" and key == node) or (
                group in ("links", "boundaries") and node in key.split("-"))
            q = after.get(name)
            if not touches or q is None or not p.get("free") or p.get("std") is None:
                continue
            shift = abs(q["value"] - p["value"])
            if shift > ABSORB_STDS * p["std"] and shift > ABSORB_SHARE * abs(p["value"]):
                out.setdefault(node, []).append(name)
    return out


# Directions whitened per call, in multiples: the residuals (1), the Jacobian (one per
# free parameter) and the candidates' directions (tens) share one program per model
# instead of compiling three (0.2 s each, in the single-threaded scoring of each step).
WHITEN_BLOCK = 32


def innovation_directions(result: FitResult, data):
    """`f(V)`: output-space directions `V` (runs, T, p, m), free-run °C, to the whitened
    innovations they cause in the fitted Kalman filter, (runs, T, p, m)
    (`fitting._likelihood.dataset_innovation_map`; linear in `V`, so its columns are
    padded with zeros to a multiple of `WHITEN_BLOCK` and cut off again)."""
    from ..fitting._likelihood import dataset_innovation_map

    def whiten(V):
        m = V.shape[-1]
        padded = np.zeros((*V.shape[:-1], -(-m // WHITEN_BLOCK) * WHITEN_BLOCK))
        padded[..., :m] = V
        return np.asarray(dataset_innovation_map(result.model, data,
                                                 jnp.asarray(padded)))[..., :m]
    return whiten


def diagnose_step(step: Step, runs: list[Telemetry], likelihood: str, *, refits: int = 3,
                  fdr: float = 0.05, say=print, white_p: float | None = None,
                  initial: ModelSpec | None = None) -> list[Candidate]:
    """Rank every candidate effect for the model of `step` (which it leaves unchanged).

    Thermal candidates are score-tested, the best `refits` of them refitted (see
    `_refit`: with `initial`, the model as the user wrote it, a refit also starts from
    the user's values, since a fit without the effect may have bent the other
    parameters to mimic it); viscoelastic ones are always refitted. With `white_p`,
    thermal candidates are only scored, not refitted, when every sensor's residuals
    are already white at that level (the misfit is in a bias channel).

    **Returns:** the candidates, refitted first, then by decreasing score."""
    spec, result = step.spec, step.result
    if white_p is not None and all(
            (step.record["whiteness_p"].get(c) or 0.0) > white_p for c in spec.sensor_columns):
        refits = 0
    unused = unused_columns(spec, runs)
    lowered = result.lowered_spec
    places = enumerate_places(spec, lowered, unused)
    thermal = [(k, w) for k, w in places if k != "viscoelastic"]
    ahead = step.scoring
    data, weights, r, J, states, whiten = (
        ahead[1].result() if ahead is not None and ahead[0] == likelihood
        else scoring_inputs(step, runs, likelihood))
    columns = _padded_columns(runs, set(unused) | set(spec.input_columns), data.ts.shape[1])
    laws = _learned_places(spec, lowered, unused, column_scales(columns))
    say(f"scoring {len(places)} candidate effects and {len(laws)} learned laws")
    try:
        cands = score_candidates(result, data, thermal + laws, columns, weights, r, J,
                                 deflation=step.deflation(white_p if white_p is not None
                                                          else 0.01), whiten=whiten,
                                 states=states)
    except Exception as err:  # scoring failure: no thermal candidate this step
        say(f"scoring failed: {type(err).__name__}: {err}")
        cands = []
    cands += _viscoelastic_candidates(step, runs, places,
                                      white_p if white_p is not None else 0.01)
    cands.sort(key=lambda c: -c.score if np.isfinite(c.score) else math.inf)

    def wave(w):
        return _refit_side_by_side(w, step, runs, likelihood, set(unused), initial, say,
                                   white_p if white_p is not None else 0.01)

    # The best learned law significant by its score is refitted too, beside the kinds
    # (never instead of them: a law may mimic a kind, and the kind is the simpler form),
    # unless a kind has the larger score or the law's shape is its nested kind's. Its
    # refit, a nonlinear model (the costliest), goes first in the kinds' first wave.
    best_law = [c for c in cands if c.learned is not None and c.p_value < fdr][:1]
    if not (refits and best_law and not _law_outranked(best_law[0], cands) and
            not _law_adds_nothing(best_law[0], cands, fdr, lowered)):
        best_law = []
    refit_best([c for c in cands if c.learned is None], refits, wave, beside=best_law)
    if best_law:
        # the kind the law reduces to (a column's heat_source), refitted too if it was
        # not: the law must beat the simpler form it nests (`prefer_vocabulary`)
        nested = best_law[0].learned.nested_kind(best_law[0].where)
        refit_best([c for c in cands if c.learned is None and c.key == nested], 1, wave)
    cands.sort(key=lambda c: (c.method != "refit",
                              -c.score if np.isfinite(c.score) else math.inf))
    judge(cands, fdr, separation_advice)
    prefer_vocabulary(cands)
    reject_unphysical(cands, data_span(spec, runs))
    prefer_physics(cands, separation_advice)
    return cands


def scoring_inputs(step: Step, runs: list[Telemetry], likelihood: str) -> tuple:
    """`(data, weights, r, J, states, whiten)` the score tests of `step` start from: the
    output-error problem at its fit (`output_error_at`); under the Kalman likelihood the
    residuals `r` and Jacobian `J` whitened by the fitted filter, and `whiten` the map
    that does it (`innovation_directions`), else None."""
    result = step.result
    data, weights, r, J, states = output_error_at(
        result, _experiments(result.lowered_spec, runs))
    weights, r, J = np.array(weights), np.array(r), np.array(J)
    whiten = None
    if likelihood == "kalman":
        # Score on the innovations: residuals, the fitted parameters' directions and
        # every candidate's direction go through the fitted filter (`innovation_map`).
        whiten = innovation_directions(result, data)
        scale = np.where(weights > 0, 1.0 / np.where(weights > 0, weights, 1.0), 0.0)
        r = whiten((r.reshape(weights.shape) * scale)[..., None]).reshape(-1)
        J = whiten(J.reshape(*weights.shape, -1) * scale[..., None]).reshape(r.size, -1)
    return data, weights, r, J, states, whiten


def score_ahead(step: Step, runs: list[Telemetry], likelihood: str) -> None:
    """Compute `step`'s `scoring_inputs` on a thread of its own (`step.scoring`), for
    `diagnose_step` to take when it scores the step: a candidate's, while its held-out
    folds are fitted, so that their programs' compilation (1-3 s a step on PRBS1) is
    off the loop's single-threaded scoring. A failure is raised where they are taken."""
    step.scoring = (likelihood, _on_thread(scoring_inputs, step, runs, likelihood))


def _law_outranked(law: Candidate, cands: list[Candidate]) -> bool:
    """Whether a kind of the vocabulary has a larger score-test statistic than the learned
    `law`: a named kind then explains more at first order, and the law's refit (a
    nonlinear model: under the Kalman likelihood the costliest fit of an investigation)
    is skipped. Notes the reason on `law`."""
    kinds = [c for c in cands if c.learned is None and c.kind != "viscoelastic"
             and c.score_test is not None and np.isfinite(c.score_test)]
    best = max(kinds, key=lambda c: c.score_test, default=None)
    if best is None or best.score_test <= law.score_test:
        return False
    law.add_note(f"not refitted: its score, {law.score_test:.4g}, is below that of "
                 f"{best.kind} {list(best.where)} ({best.score_test:.4g}): a named kind "
                 "explains more")
    return True


def _law_adds_nothing(law: Candidate, cands: list[Candidate], fdr: float,
                      lowered: ModelSpec | None = None) -> bool:
    """Whether the learned `law`'s best score direction gains less over the kind of the
    vocabulary it nests than the χ²(1) critical value at `fdr` (the shape chosen from
    its grid is the one extra degree of freedom): its shape is then the nested kind's,
    and its refit, a nonlinear model (the costliest of a step), could only tie with the
    kind, which `prefer_vocabulary` keeps. Likewise when its best shape is the nested
    kind's and the model (`lowered`) already has that kind there: the score then finds
    nothing in the law's own shapes, only in a heat the model has (on PRBS1 the law
    `c·Ps^p·exp(k(Ti − 25))` at p = 1, k = 0 is the model's solar gain on Ti; it scored
    489 and 351 from the half-sample shift between how score tests and the model hold
    `Ps`, and its refits, 25 s of the loop, gained 56 and 46, both rejected).
    Notes the reason on `law`."""
    nested = law.learned.nested_kind(law.where)
    if (nested is not None and lowered is not None and law.learned.is_nested_shape(law.shape)
            and KINDS[nested[0]].held_by(lowered, nested[1])):
        shape = ", ".join(f"{n} = {v:g}" for n, v in zip(law.learned.term.shape, law.shape))
        law.add_note(f"not refitted: its best shape ({shape}) makes it {nested[0]} "
                     f"{list(nested[1])}, a heat the model already has: the score finds "
                     "nothing in the law's own shapes")
        return True
    kind = next((c for c in cands if c.learned is None and c.key == nested), None)
    if kind is None or kind.score_test is None:
        return False
    gain = law.score_test - kind.score_test
    critical = float(stats.chi2.isf(fdr, 1))
    if gain >= critical:
        return False
    law.add_note(f"not refitted: its score exceeds that of {kind.kind} {list(kind.where)}, "
                 f"the kind it nests, by {gain:.3g} (under {critical:.3g}, the χ²(1) "
                 f"critical value at {fdr:g}): its best shape is the kind's, which explains "
                 "as much")
    return True


def _learned_places(spec: ModelSpec, lowered: ModelSpec, unused: dict[str, str],
                    scales: dict[str, float]) -> list:
    """The library's laws at every place (`discovery.learned_places`): the unused columns
    and the model's own power columns as inputs (read in `scales`), except a law the
    model already holds."""
    roles = {**unused, **{h.input: "power" for h in spec.heat_inputs}}
    have = {(tuple(e.where), e.expression) for e in spec.effects if e.kind == "expression"}
    helpers = helper_nodes(spec, lowered)
    return [(law, where) for law, where in learned_places(lowered, roles, scales)
            if (tuple(where), law.text(where)) not in have and not helpers & set(where)]


SEPARATION = {
    frozenset(("sensor_lag", "extra_node")):
        "a lag acts on the reading alone, a mass also delays the heat reaching the rest of "
        "the network: a second sensor on (or beyond) that node, or a known power step into "
        "it, would separate them",
    frozenset(("radiation", "conductance_temperature")):
        "both strengthen the path as it warms; radiation grows with T³ in kelvin, a linear "
        "temperature coefficient with T̄ − 25 °C: runs over a wider temperature range "
        "(or in vacuum) would separate them",
}


def separation_advice(kinds) -> str:
    kinds = frozenset(kinds)
    for pair, text in SEPARATION.items():
        if pair <= kinds or (len(kinds) == 1 and kinds <= pair):
            return text
    if kinds & {"sensor_gain", "sensor_offset"}:
        return ("a sensor's gain or offset changes its reading alone, a thermal effect the "
                "temperatures themselves: a reference thermometer beside the sensor, read at "
                "two steady temperatures (a soak at each end of the range), separates them")
    return ("the data cannot tell these apart: excite the system differently (a power step "
            "in the node concerned, a faster ramp, a wider temperature range) or add a sensor "
            "near the candidates' places")


def holdout_folds(runs: list[Telemetry], n_blocks: int = N_BLOCKS) -> list[tuple]:
    """The held-out folds: `(run, None)` for each run with three runs or more, else
    `(run, (start, stop))` sample spans cutting the runs into about `n_blocks` contiguous
    blocks in all (blocked cross-validation)."""
    if len(runs) >= 3:
        return [(r, None) for r in range(len(runs))]
    per = -(-n_blocks // len(runs))
    out = []
    for r, t in enumerate(runs):
        edges = np.linspace(0, len(t.ts), per + 1).astype(int)
        out += [(r, (int(a), int(b))) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    return out


def _held_rows(fold, n: int) -> slice:
    return slice(0, n) if fold[1] is None else slice(*fold[1])


# A held-out fit starts at the fit to all the data (`spec`'s values): a warm start, whose
# first Gauss-Newton steps are already good, so its damping starts a thousand times
# lower than a cold start's (on imu6 the folds take 2-4 steps fewer each).
_WARM_START = TruncatedGaussNewton(initial_damping=1e-6)


def _fit_without(spec, experiments, fold, likelihood="output_error"):
    """Fit of `spec` (its values those of the fit to all the data) with the fold's
    measurements masked; its predictions still cover them (the free run, or the filter,
    goes through the held-out block). A Kalman fold fit ends after its scoring steps (no
    polish: from that warm start it would walk the full fit's valleys again for a few
    0.1 of −log L, most of a loop's time on PRBS1). A warm start that does not converge
    is tried once more with the default solver; a fit that still does not converge is
    returned as it is (`fold_vote` sets its fold aside)."""
    r, span = fold
    if span is None:
        masked = experiments
    else:
        e = experiments[r]
        y = np.array(e.outputs, float)
        y[span[0]:span[1]] = np.nan
        masked = [*experiments[:r], dataclasses.replace(e, outputs=y), *experiments[r + 1:]]
    holdout = r if span is None else None
    for solver in ((_WARM_START, None) if likelihood == "output_error" else (None,)):
        res = fit(spec, masked, likelihood=likelihood, holdout=holdout, solver=solver,
                  restart_plateaus=False, polish=False)
        if res.converged:
            break
    if not np.isfinite(res.nll) or not all(np.all(np.isfinite(p)) for p in res.predictions):
        raise FloatingPointError("the held-out fit went non-finite")
    return res


def held_out_terms(res, experiments, fold, rows, sigma, likelihood) -> np.ndarray:
    """Per held-out sample, its −log L term under a fit made without the fold: half the
    squared free-run residuals over `sigma` summed over the outputs (output error; the
    constant terms cancel between models), or, under the Kalman likelihood, the filter run
    through every sample with those parameters and each held-out sample's one-step
    predictive term (prequential). Missing readings contribute nothing."""
    r = fold[0]
    if likelihood == "kalman":
        from ..fitting._likelihood import kalman_sample_nll
        from ..measurements._data import Dataset

        data = Dataset.from_experiments(experiments)
        per = np.asarray(kalman_sample_nll(res.model, data, res.state.run_initial))
        return per[r, :len(experiments[r].ts)][rows]
    e = (experiments[r].outputs[rows] - res.predictions[r][rows]) / sigma[None, :]
    return 0.5 * np.nansum(e ** 2, axis=1)


def _unconverged(res) -> str:
    return "" if getattr(res, "converged", True) else \
        f"a held-out fit did not converge ({getattr(res, 'message', '')})"


class HeldOutFits:
    """`_fit_without` of one loop's runs, kept: the model a step adds is the next step's
    base, held out on the same folds, so its fits are made once. A fit that raised is
    kept as its exception."""

    def __init__(self):
        self._done: list[tuple] = []  # (spec, fold, likelihood, FitResult or exception)

    def _kept(self, spec, fold, likelihood):
        for s, f, lk, res in self._done:
            if f == fold and lk == likelihood and s == spec:
                return res
        return None

    def __call__(self, spec, experiments, fold, likelihood):
        res = self._kept(spec, fold, likelihood)
        if res is None:
            self.make([(spec, experiments, fold)], likelihood)
            res = self._kept(spec, fold, likelihood)
        return res

    def make(self, wanted: list[tuple], likelihood) -> None:
        """Make the fits `(spec, experiments, fold)` of `wanted` not made yet, side by
        side (`fitting._side_by_side`); a fit that raises is kept as its exception."""
        missing = [w for w in wanted if self._kept(w[0], w[2], likelihood) is None]

        def attempt(*args):
            try:
                return _fit_without(*args)
            except Exception as err:  # the fold is inconclusive, not the candidate
                return err

        made = side_by_side([functools.partial(attempt, *w, likelihood) for w in missing])
        self._done += [(s, fold, likelihood, res) for (s, _, fold), res in zip(missing, made)]


def _thermal_fold_votes(spec_base, spec_ext, runs, sigma, folds, say, likelihood,
                        fits: HeldOutFits) -> list[FoldVote]:
    experiments = {id(s): _experiments(s, runs) for s in (spec_base, spec_ext)}
    fits.make([(s, experiments[id(s)], fold) for fold in folds for s in (spec_base, spec_ext)],
              likelihood)
    votes = []
    for fold in folds:
        rows = _held_rows(fold, len(runs[fold[0]].ts))
        terms = []
        for s in (spec_base, spec_ext):
            res = fits(s, experiments[id(s)], fold, likelihood)
            why = "" if isinstance(res, Exception) else _unconverged(res)
            terms.append(res if isinstance(res, Exception) else RuntimeError(why) if why else
                         held_out_terms(res, experiments[id(s)], fold, rows, sigma,
                                        likelihood))
        votes.append(fold_vote(fold, *terms))
        _say_vote(say, votes[-1])
    return votes


def _say_vote(say, v: FoldVote) -> None:
    say(f"held-out fold {v.fold}: −log L change {-v.gain:.1f}" +
        (f" (inconclusive: {v.inconclusive})" if v.inconclusive else ""))


def _viscoelastic_fold_votes(current: Step, c: Candidate, runs, folds, say) -> list[FoldVote]:
    """Held-out gains of a viscoelastic term, fitted on its bias channel with the fold's
    bias samples masked (a whole held-out run keeps its first sample), on the current
    thermal states."""
    bias = next(b for b in current.spec.biases if b.column == c.where[1])
    base_runs, rates = _bias_runs(current.result, runs, bias)
    node_names = list(current.result.lowered_spec.node_names)
    sigma = float(current.biases[bias.column].sigma)
    votes = []
    for fold in folds:
        r = fold[0]
        rows = _held_rows(fold, len(runs[r].ts))
        masked = list(base_runs)
        ts, x, y = masked[r]
        ym = np.array(y, float)
        ym[rows] = np.nan
        if fold[1] is None:
            ym[0] = y[0]
        masked[r] = (ts, x, ym)
        try:
            before = fit_bias(bias, list(current.spec.effects), masked, node_names, rates)
            after, _ = viscoelastic_candidate(bias, list(current.spec.effects), masked,
                                              node_names, c.where[0], node_rates=rates)
        except Exception as err:  # this fold is inconclusive, not the candidate
            votes.append(fold_vote(fold, err, err))
            _say_vote(say, votes[-1])
            continue
        terms = [0.5 * np.nan_to_num(((y[rows] - f.predictions[r][rows]) / sigma) ** 2,
                                     nan=0.0, posinf=np.inf)
                 for f in (before, after)]
        votes.append(fold_vote(fold, *terms))
        _say_vote(say, votes[-1])
    return votes


# ---------------------------------------------------------------------------
# The loop


def check_holdout(c: Candidate, current: Step, runs, likelihood, say,
                  fits: HeldOutFits) -> None:
    """The held-out check of a candidate that passed the likelihood-ratio rule
    (`_selection.holdout_verdict`): its fold votes, summed gain and verdict go into `c`;
    a rejected candidate is marked unsupported with the reason."""
    folds = holdout_folds(runs)
    if c.kind == "viscoelastic":
        votes = _viscoelastic_fold_votes(current, c, runs, folds, say)
    else:
        sigma = np.array([current.record["parameters"].get(
            f"sensors.{s}.noise", {"value": 0.01})["value"]
            for s in current.spec.sensor_columns])
        votes = _thermal_fold_votes(current.spec, c.result.spec, runs, sigma,
                                    folds, say, likelihood, fits)
    ok, c.holdout_gain, why = holdout_verdict(votes)
    c.holdout_votes = votes
    scheme = "leave one run out" if folds[0][1] is None else f"{len(folds)} contiguous blocks"
    if ok is False:
        c.supported = False
        c.add_note(f"held-out check against it ({scheme}): {why}", first=True)
    else:
        c.add_note(f"{why} ({scheme})", first=True)


def _choose(cands: list[Candidate], current: Step, runs, likelihood, holdout_check: bool,
            say, fits: HeldOutFits, checking=None) -> Candidate | None:
    """The first supported candidate that (with `holdout_check`) the held-out check does
    not reject (`check_holdout`) and whose extended model could be built; the others it
    tries are marked unsupported, with the reason. On return `chosen.result` holds the
    extended step. `fits`: the loop's held-out fits so far; `checking(c)`: called as the
    held-out check of a refitted candidate starts (its figures are drawn meanwhile)."""
    for c in cands:
        if not c.supported:
            continue
        try:
            if holdout_check:
                if checking is not None and isinstance(c.result, Step):
                    checking(c)  # a thermal candidate's extended step
                check_holdout(c, current, runs, likelihood, say, fits)
                if not c.supported:
                    continue
            if c.kind == "viscoelastic":
                c.result = _viscoelastic_step(current, c, runs, likelihood)
        except Exception as err:  # a failed extended fit rejects the candidate
            c.supported = False
            c.note = f"held-out or extended fit failed: {type(err).__name__}: {err}"[:300]
            continue
        return c
    return None


def _viscoelastic_step(current: Step, c: Candidate, runs, likelihood) -> Step:
    from ..model._spec import Effect, Parameter

    eff = Effect("viscoelastic", c.where, {k: Parameter(v) for k, v in c.parameters.items()})
    return evaluate(current.spec.replace(effects=current.spec.effects + (eff,)), runs,
                    likelihood)


def confirmed_optimum(step: Step, runs, likelihood, say) -> Step:
    """`step`, or a better fit of its model from `N_STARTS` output-error starts (the first
    at its fitted values, the others perturbed): a step is scored only from a fit that
    is not a local optimum. The gain goes into the record (`multistart_gain`, −log L).

    A step whose fit is already the best of `N_STARTS - 1` or more starts (the refit of
    the candidate it added: from the fitted values with the effect, the user's values,
    the score's time constant) has had its check: on PRBS1 the check of such a step
    never gained (at most 6e-6 at steps 1-3, under `MULTISTART_TOL`) and cost 8 s of
    the loop, 6 s at its first nonlinear model (an output-error program of its own)."""
    if step.starts >= N_STARTS - 1:
        return step
    try:
        again = evaluate(step.spec, runs, likelihood, n_starts=N_STARTS)
    except Exception as err:  # the step's own fit stands
        say(f"multi-start check failed: {type(err).__name__}: {err}")
        return step
    gain = step.record["nll"] - again.record["nll"]
    if gain > MULTISTART_TOL:
        say(f"multi-start: a better optimum, −log L lower by {gain:.3f}")
        again.record["added"] = step.record["added"]
        step = again
    step.record["multistart_gain"] = float(max(gain, 0.0))
    return step


def _added(c: Candidate) -> dict:
    """The `added` entry of the record of the step that adds `c` (`c.result`)."""
    added = added_effect(c.result.spec, c)
    return {"kind": added.kind, "where": list(added.where),
            **({"expression": added.expression} if added.expression else {}),
            "parameters": {k: p.value for k, p in added.parameters.items()},
            **({"name": added.name} if added.name else {}),
            **({"hold": added.hold} if added.hold else {})}


def _extend(current: Step, chosen: Candidate, runs, likelihood) -> Step:
    """The next step: the extended step `_choose` built for `chosen`, its record's `added`
    filled in."""
    nxt = chosen.result
    nxt.record["added"] = _added(chosen)
    return nxt


def record_missing_heat(step: Step, out: Path | None, i: int, white_p: float, say):
    """When a column of `step` is not white, reconstruct the missing heat
    (`discovery.missing_heat`), write it as `step<i>_missing_heat.csv` in `out` and put
    its summary in the step's record (`missing_heat`). A failure is a note, not the end
    of the loop.

    **Returns:** the `MissingHeat`, or None (white, or the reconstruction failed)."""
    from ..discovery import missing_heat, write_missing_heat

    rec = step.record
    if all(p is not None and p > white_p for p in rec["whiteness_p"].values()):
        return None
    say(f"step {i}: reconstructing the missing heat")
    try:
        mh = missing_heat(step.result, say=say)
        name = f"step{i}_missing_heat.csv"
        if out is not None:
            write_missing_heat(mh, Path(out) / name)
        rec["missing_heat"] = mh.summary(name if out is not None else None)
        return mh
    except Exception as err:  # the reconstruction could not run: say why
        rec["missing_heat"] = {"file": None,
                               "note": f"could not reconstruct: {type(err).__name__}: {err}"[:300]}
        say(rec["missing_heat"]["note"])
        return None


def _on_thread(fn, *args) -> Future:
    """`fn(*args)` started on a thread of its own; its `Future`."""
    pool = ThreadPoolExecutor(1, thread_name_prefix="thermojax-beside")
    future = pool.submit(fn, *args)
    pool.shutdown(wait=False)
    return future


def _beside(task, *args, say):
    """Start `task(*args, say)` on a thread of its own; returns `wait()`, which waits
    for it, says what it said (held till then, so that its lines do not interleave with
    the step's) and returns its result. The missing heat, which only the step's end reads,
    so runs beside the candidates' scoring and refits: its single-threaded programs fill
    the core the refits leave idle at their waves' ends (5 s a step on PRBS1)."""
    said: list[str] = []
    future = _on_thread(task, *args, said.append)

    def wait():
        try:
            return future.result()
        finally:
            for line in said:
                say(line)
    return wait


def _network_step(current: Step, runs, mh, cands: list[Candidate], likelihood, fdr,
                  white_p, initial, holdout_check, say, held_out) -> Candidate | None:
    """When no candidate was supported: the heat network's proposal
    (`_network_candidate`), refitted and judged beside the step's candidates (the
    family of Benjamini-Hochberg holds them all; their own verdicts stand) and, if
    supported, held-out checked like any other. Its account goes into the step's
    record (`network`); a network that cannot run is a note, not the end of the loop.

    **Returns:** the chosen candidate, or None."""
    from ._network_candidate import network_candidate

    try:
        cand, current.record["network"] = network_candidate(current, runs, mh, say)
    except Exception as err:
        current.record["network"] = {
            "verdict": f"the heat network could not run: {type(err).__name__}: {err}"[:300]}
        say(current.record["network"]["verdict"])
        return None
    if cand is None:
        return None
    _refit_side_by_side([cand], current, runs, likelihood,
                        set(unused_columns(current.spec, runs)), initial, say, white_p)
    cand.add_note(f"proposed by the heat network at {current.record['network']['node']}",
                  first=True)  # after the refit, which writes its own note
    kept = [(c.supported, c.note, c.tied_with) for c in cands]
    judge(cands + [cand], fdr, separation_advice)
    prefer_vocabulary(cands + [cand])
    reject_unphysical([cand], data_span(current.spec, runs))
    for c, (supported, note, tied) in zip(cands, kept):
        c.supported, c.note, c.tied_with = supported, note, tied
    cands.append(cand)
    return _choose([cand], current, runs, likelihood, holdout_check, say, held_out)


def record_unexplained(step: Step, mh, say) -> None:
    """The step's `unexplained` list (spec §3a) when no candidate, of the vocabulary or
    the library, explained its non-white residuals: the missing heat described."""
    from ..discovery import unexplained

    if mh is None:
        return
    step.record["unexplained"] = unexplained(mh, step.record["missing_heat"]["file"])
    net = step.record.get("network") or {}
    for u in step.record["unexplained"]:
        if u["where"] == [net.get("node")] and "verdict" in net:
            u["network"] = net["verdict"]  # what the heat network made of it
        say(f"unexplained at {u['where'][0]}: {u['what']}")


def _unexplained(record: dict, white_p: float) -> str:
    bad = [c for c, p in record["whiteness_p"].items() if p is None or p <= white_p]
    return (f"the residuals of {', '.join(bad)} stay non-white: part of the error "
            "is not explained by any effect of the vocabulary with the data "
            "columns given (an unrecorded input, or physics outside the "
            "vocabulary).")


@one_blas_thread()  # XLA's pool and the fits' threads use the cores (`_blas_threads`)
def investigate(spec: ModelSpec, runs: list[Telemetry], *, likelihood: str = "output_error",
                max_steps: int = 4, refits: int = 3, fdr: float = 0.05,
                white_p: float = 0.01, out: Path | None = None, progress=None,
                resume: bool = True, holdout_check: bool = True, network: bool = True
                ) -> dict:
    """Run the loop; returns the `report.json` dict (docs/formats.md §5). With `out`, writes the
    report, every step's model, `model_final.toml`, the Markdown report and its plots,
    and a checkpoint after each finished step, from which a rerun resumes. With
    `network`, a step that finds nothing supported while heat is missing asks a heat
    network before it stops (`_network_step`)."""
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    out = Path(out) if out is not None else None
    inputs = _inputs(spec, runs, likelihood)
    records: list[dict] = []
    start_spec = spec
    if out is not None and resume:
        records, start_spec = _load_checkpoint(out, inputs, spec)
        if records:
            say(f"resuming after step {len(records) - 1} from {out / 'checkpoint.json'}")
    if out is not None and not records and out.is_dir():
        _clear_earlier_run(out)
    current = evaluate(start_spec, runs, likelihood, progress=None)
    if records:
        current.record["added"] = records[-1]["added"]
        records[-1] = {**current.record, "candidates": [], "wall_time_s":
                       records[-1].get("wall_time_s")}
    else:
        records.append(current.record)
    steps_traces = [None] * (len(records) - 1) + [current.traces]
    heat_series = [None] * len(records)  # per step its MissingHeat, for the report's figure
    held_out = HeldOutFits()
    plots = PlotsAhead() if out is not None else None
    stopped, advice = "max_steps", None
    try:
        while True:
            i = len(records) - 1
            rec = records[-1]
            say(f"step {i}: −log L {rec['nll']:.1f}, RMSE " +
                ", ".join(f"{c} {v:.4g}" for c, v in rec["rmse"].items()))
            if all(p is not None and p > white_p for p in rec["whiteness_p"].values()):
                stopped = "residuals_white"
                break
            if i >= max_steps:
                stopped = "max_steps"
                break
            t_step = time.perf_counter()
            current = confirmed_optimum(current, runs, likelihood, say)
            records[-1] = rec = current.record
            steps_traces[-1] = current.traces
            _plot_ahead(plots, out, i, current)
            if out is not None:
                out.mkdir(parents=True, exist_ok=True)
            missing = _beside(record_missing_heat, current, out, i, white_p, say=say)
            cands = diagnose_step(current, runs, likelihood, refits=refits, fdr=fdr, say=say,
                                  white_p=white_p, initial=spec)
            def checking(c, i=i):  # while a candidate's held-out folds are fitted
                _plot_ahead(plots, out, i + 1, c.result, _added(c))
                if i + 1 < max_steps:  # the step it would make is scored next
                    score_ahead(c.result, runs, likelihood)

            chosen = _choose(cands, current, runs, likelihood, holdout_check, say, held_out,
                             checking)
            missing = heat_series[-1] = missing()
            if chosen is None and network and missing is not None and missing.carriers:
                chosen = _network_step(current, runs, missing, cands, likelihood, fdr,
                                       white_p, spec, holdout_check, say, held_out)
            rec["candidates"] = [c.as_json() for c in cands]
            rec["wall_time_s"] = time.perf_counter() - t_step
            if chosen is not None and chosen.tied_with:
                rec["separation"] = separation_advice({chosen.kind, *(k for k, _ in
                                                                       chosen.tied_with)})
            if chosen is None:
                record_unexplained(current, missing, say)
                advice = held_out_advice(cands, likelihood)
                stopped = "no_supported_candidate"
                break
            current = _extend(current, chosen, runs, likelihood)
            say(f"added {chosen.kind} {list(chosen.where)}")
            records.append(current.record)
            steps_traces.append(current.traces)
            heat_series.append(None)
            if out is not None:
                _save_checkpoint(out, inputs, records, current.spec)
            release_compiled_if_crowded()  # rejected candidates' programs are not reused
        report = _report(records, stopped, likelihood, fdr, white_p,
                         time.perf_counter() - t0)
        report["noise"] = _noise(current)
        if advice:
            report["advice"] = advice
        if out is not None:
            _write_outputs(out, report, current, steps_traces, runs, plots, heat_series)
        return json_safe(report)
    finally:
        if plots is not None:
            plots.close()


def _report(records: list[dict], stopped: str, likelihood: str, fdr: float,
            white_p: float, wall_time_s: float) -> dict:
    """The `report.json` dict (docs/formats.md §5) but its `noise`."""
    return {
        "schema": 1, "thermojax_version": _version(), "likelihood": likelihood,
        "steps": records, "stopped_because": stopped, "final_model": "model_final.toml",
        "unexplained": (None if stopped == "residuals_white"
                        else _unexplained(records[-1], white_p)),
        "significance_rule": significance_rule(fdr, N_BLOCKS),
        "whiteness_test": ("Ljung-Box of the "
                           + ("one-step innovations" if likelihood == "kalman"
                              else "free-run residuals")
                           + ", lags min(20, N/5), runs pooled by summing per-run "
                           f"autocovariances; white when p > {white_p} for every column"),
        "white_p": white_p,  # the threshold of `residuals_white`, for the report's verdicts
        "wall_time_s": wall_time_s,
    }


def _noise(step: Step) -> dict:
    out = {}
    for c in step.spec.sensor_columns:
        p = step.record["parameters"].get(f"sensors.{c}.noise")
        if p is not None:
            out[c] = p["value"]
    for c, f in step.biases.items():
        out[c] = float(f.sigma)
    return out


def _version() -> str:
    from .. import __version__

    return __version__


def _inputs(spec, runs, likelihood) -> dict:
    """What an investigation's result depends on, by content: the model file's text, the
    likelihood, and per run the SHA-256 of its times and every column's name and values
    (a data file edited in place changes it; the same data moved elsewhere does not)."""
    def digest(t: Telemetry) -> str:
        h = hashlib.sha256(np.ascontiguousarray(t.ts, dtype=np.float64).tobytes())
        for name, values in t.channels.items():
            h.update(name.encode() + b"\0")
            h.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
        return h.hexdigest()

    return {"model": hashlib.sha256(dump_model(spec).encode()).hexdigest(),
            "likelihood": likelihood,
            "runs": [{"path": str(t.path), "sha256": digest(t)} for t in runs]}


def _fingerprint(inputs: dict) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


def _what_changed(old: dict, new: dict) -> str:
    """The differences between two `_inputs`, in words."""
    if not old:
        return "the checkpoint was written by an earlier thermojax version"
    out = []
    if old.get("model") != new["model"]:
        out.append("the model")
    if old.get("likelihood") != new["likelihood"]:
        out.append(f"the likelihood ({old.get('likelihood')} → {new['likelihood']})")
    before, after = old.get("runs", []), new["runs"]
    if len(before) != len(after):
        out.append(f"the number of data files ({len(before)} → {len(after)})")
    else:
        out += [f"the data of {b['path']}" + (f" (now {a['path']})" if a["path"] != b["path"]
                                              else "")
                for b, a in zip(before, after) if b["sha256"] != a["sha256"]]
    return ", ".join(out) or "the inputs"


def _save_checkpoint(out: Path, inputs: dict, records, spec) -> None:
    out.mkdir(parents=True, exist_ok=True)
    i = len(records) - 1
    save_model(spec, out / f"step{i}_model.toml",
               header=f"thermojax investigate: model after step {i}")
    tmp = out / "checkpoint.json.tmp"
    tmp.write_text(json.dumps(json_safe({"fingerprint": _fingerprint(inputs), "inputs": inputs,
                                          "steps": records, "model": f"step{i}_model.toml"})))
    tmp.replace(out / "checkpoint.json")


def _load_checkpoint(out: Path, inputs: dict, spec):
    """`(records, model)` to resume from `out`'s checkpoint, `([], spec)` when there is none.
    A checkpoint of other inputs is refused (`InputError`, saying what changed): resuming
    would mix steps of two investigations."""
    from ..model._model_file import load_model

    path = out / "checkpoint.json"
    if not path.exists():
        return [], spec
    try:
        doc = json.loads(path.read_text())
        stored = doc.get("fingerprint")
    except (OSError, ValueError) as err:
        raise InputError(f"its checkpoint cannot be read ({err}); pass --restart to start "
                         "afresh (the finished steps there are discarded).",
                         file=str(path)) from None
    if stored != _fingerprint(inputs):
        raise InputError(
            f"holds an investigation of other inputs: {_what_changed(doc.get('inputs'), inputs)} "
            "changed since its steps were made. Resuming would mix the two; pass --restart to "
            "start afresh from the given model (its finished steps are discarded), or choose "
            "another --out.", file=str(out))
    try:
        return doc["steps"], load_model(out / doc["model"])
    except (OSError, ValueError, KeyError) as err:
        raise InputError(f"its checkpoint names a model that cannot be read ({err}); pass "
                         "--restart to start afresh.", file=str(path)) from None


STALE = ("checkpoint.json", "step*_*", "report.json", "report.md", "model_final.toml")


def _clear_earlier_run(out: Path) -> None:
    """Remove what an earlier investigation left in `out` (its steps, checkpoint, report),
    so a fresh start leaves nothing of it beside the new report."""
    for pattern in STALE:
        for f in out.glob(pattern):
            if f.is_file():
                f.unlink()


def _report_columns(spec: ModelSpec) -> tuple[list, list, list, dict]:
    """`(columns, inputs, boundary inputs, units)` the report and its figures use for
    `spec`: sensor columns then bias columns, input columns, boundary columns, and
    `_plots.column_units`."""
    from .._plots import column_units

    bias = [b.column for b in spec.biases]
    return (list(spec.sensor_columns) + bias, list(spec.input_columns),
            list(spec.boundary_columns), column_units(spec.sensor_columns, bias))


def _plot_ahead(plots: PlotsAhead | None, out: Path, i: int, step: Step,
                added: dict | None = None) -> None:
    """Queue step `i`'s figures on `plots` against its own model's columns (the report
    draws them again only if the final model reads other columns). With `added` (its
    record's `added`, `_added`), `step` is a candidate's, not yet taken: its figures are
    staged until the report asks for them."""
    from ._investigation_report import step_plot_options

    if plots is None or not step.traces:
        return
    record = step.record if added is None else {**step.record, "added": added}
    cols, inputs, boundary, units = _report_columns(step.spec)
    plots.ahead(out, f"step{i}", cols, step.traces, inputs, boundary, units=units,
                staged=added is not None, **step_plot_options(i, json_safe(record)))


def _write_outputs(out: Path, report: dict, final: Step, traces, runs,
                   plots: PlotsAhead | None = None, heat_series=None) -> None:
    from ._investigation_report import write_investigation_report
    from ._missing_heat_plots import nearest_sensors

    out.mkdir(parents=True, exist_ok=True)
    save_model(final.spec, out / "model_final.toml",
               header="thermojax investigate: the final model")
    tmp = out / "report.json.tmp"  # whole or not at all: a reader never sees half of it
    tmp.write_text(json.dumps(json_safe(report), indent=2, allow_nan=False))
    tmp.replace(out / "report.json")
    cols, inputs, boundary, units = _report_columns(final.spec)
    for step_traces in traces:  # every step's plots against the final model's inputs
        for r, tr in enumerate(step_traces or []):
            tr["inputs"] = np.stack([runs[r].column(c) for c in inputs], 1) if inputs \
                else np.zeros((len(tr["ts"]), 0))
    watts = {h.input: "W" for h in final.spec.heat_inputs}
    write_investigation_report(out, json_safe(report), [t or [] for t in traces], cols,
                               inputs, boundary, units=units, plots_ahead=plots,
                               missing_heat=heat_series, nearest=nearest_sensors(final.spec),
                               input_units=watts)
