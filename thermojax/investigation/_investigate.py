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

This file is the loop itself; each of its parts is a file of its own: a step's model
fitted and measured (`_step`), its candidates scored and ranked (`_diagnose_step`),
refitted (`_refits`, `_refit_verdicts`; the learned laws screened first,
`_laws_screen`), held out (`_held_out`), its missing heat (`_missing_heat_step`), the
work done beside the step on threads (`_background`), the checkpoint (`_checkpoint`)
and what is written (`_outputs`).
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ._background import _beside, score_ahead
from ._candidates import Candidate
from ._checkpoint import (_clear_earlier_run, _inputs, _load_checkpoint, _load_step_series,
                          _save_checkpoint, _save_step_series)
from ._diagnose_step import diagnose_step
from ._held_out import HeldOutFits, _choose
from ._missing_heat_step import _file_values_step, _network_step, record_missing_heat, \
    record_unexplained
from ._outputs import _noise, _plot_ahead, _report, _write_outputs
from ._phase_times import COMPILATION, phase, phases_in_words, step_phases
from ._plots_ahead import PlotsAhead
from ._refit_verdicts import added_effect
from ._selection import held_out_advice
from ._separation import separation_advice
from ._step import Step, confirmed_optimum, evaluate
from ._step_estimate import (DEARER, RefitCosts, duration_text, expected_step_seconds,
                             refit_cost_ratio, refit_forecast)
from ._symbolic_step import SearchSettings, record_evidence
from .._blas_threads import one_blas_thread
from ..fitting._hold_check import better_holds, with_hold
from .._json import json_safe
from .._memory import release_compiled_if_crowded
from ..measurements._telemetry import Telemetry
from ..model._spec import ModelSpec


def _added(c: Candidate) -> dict:
    """The `added` entry of the record of the step that adds `c` (`c.result`)."""
    added = added_effect(c.result.spec, c)
    return {"kind": added.kind, "where": list(added.where),
            **({"replaces": list(c.replaced)} if c.replaced else {}),
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


@dataclass
class _Loop:
    """What every step of one investigation works with: the model as the user wrote it
    (a refit also starts from its values), the runs, the settings of `investigate`, the
    held-out fits kept from step to step and the figures drawn ahead."""

    spec: ModelSpec
    runs: list[Telemetry]
    likelihood: str
    max_steps: int
    refits: int
    fdr: float
    white_p: float
    holdout_check: bool
    network: bool
    out: Path | None
    say: Callable[[str], None]
    held_out: HeldOutFits
    plots: PlotsAhead | None
    search: SearchSettings | None = None
    # What a fit of the last chosen structure cost against the last step's average refit
    # (`refit_cost_ratio`): the next step's refits all extend that structure.
    cost_ratio: float = 1.0
    # What the last step's refits cost (`RefitCosts`), for the forecast once scored.
    refit_costs: RefitCosts | None = None


@one_blas_thread()  # XLA's pool and the fits' threads use the cores (`_blas_threads`)
def investigate(spec: ModelSpec, runs: list[Telemetry], *, likelihood: str = "output_error",
                max_steps: int = 4, refits: int = 3, fdr: float = 0.05,
                white_p: float = 0.01, out: Path | None = None, progress=None,
                resume: bool = True, holdout_check: bool = True, network: bool = True,
                search: SearchSettings | None = None) -> dict:
    """Run the loop; returns the `report.json` dict (docs/formats.md §5). With `out`, writes the
    report, every step's model, `model_final.toml`, the Markdown report and its plots,
    and a checkpoint after each finished step, from which a rerun resumes. With
    `network`, a step that finds nothing supported while heat is missing asks a heat
    network before it stops (`_network_step`). With `search` (its budget, e.g.
    `SearchSettings()`; None, the default: none), a step whose residuals are not white
    searches laws of its missing heat, whose best are candidates beside the others
    (`_symbolic_step`)."""
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    out = Path(out) if out is not None else None
    inputs = _inputs(spec, runs, likelihood)
    records, current = _first_step(spec, runs, likelihood, out, inputs, resume, say)
    # per step its traces and MissingHeat, for the report's figures (a resumed run reads
    # the finished steps' from the files the interrupted one saved)
    steps_traces, heat_series = _load_step_series(out, len(records) - 1)
    steps_traces.append(current.traces)
    heat_series.append(None)
    loop = _Loop(spec, runs, likelihood, max_steps, refits, fdr, white_p, holdout_check,
                 network, out, say, HeldOutFits(), PlotsAhead() if out is not None else None,
                 search)
    advice = None
    try:
        while (stopped := _stops_before(loop, records)) is None:
            t_step = time.perf_counter()
            _say_expected(loop, records)
            with step_phases() as phases:
                with phase("multi-start check"):
                    current = confirmed_optimum(current, runs, likelihood, say)
                records[-1] = current.record
                steps_traces[-1] = current.traces
                cands, chosen, heat_series[-1] = _step_candidates(loop, current,
                                                                  len(records) - 1)
            _record_candidates(current.record, cands, chosen, t_step, phases)
            say(f"step {len(records) - 1} took "
                + phases_in_words(phases, current.record["wall_time_s"]))
            if chosen is None:
                record_unexplained(current, heat_series[-1], say)
                advice = held_out_advice(cands, likelihood)
                stopped = "no_supported_candidate"
                break
            loop.cost_ratio = refit_cost_ratio(chosen, cands)
            loop.refit_costs = RefitCosts.measured(cands, phases.get("refits", 0.0),
                                                   current.result.model.is_nonlinear)
            current = _extend(current, chosen, runs, likelihood)
            say(f"added {chosen.kind} {list(chosen.where)}")
            records.append(current.record)
            steps_traces.append(current.traces)
            heat_series.append(None)
            if out is not None:
                _save_step_series(out, len(records) - 2, steps_traces[-2], heat_series[-2])
                _save_checkpoint(out, inputs, records, current.spec)
            release_compiled_if_crowded()  # rejected candidates' programs are not reused
        return _finish(loop, records, stopped, advice, current, steps_traces, heat_series,
                       time.perf_counter() - t0)
    finally:
        if loop.plots is not None:
            loop.plots.close()


def _first_step(spec, runs, likelihood, out, inputs, resume, say) -> tuple[list[dict], Step]:
    """`(records, step)`: the loop's records so far and the step it goes on from, fitted:
    step 0 (the given model), or resuming from `out`'s checkpoint (`resume`), its last
    finished step. A fresh start in an existing `out` clears an earlier run's files."""
    records: list[dict] = []
    start_spec = spec
    if out is not None and resume:
        records, start_spec = _load_checkpoint(out, inputs, spec)
        if records:
            say(f"resuming after step {len(records) - 1} from {out / 'checkpoint.json'}")
    if out is not None and not records and out.is_dir():
        _clear_earlier_run(out)
    current = evaluate(start_spec, runs, likelihood, progress=None)
    if not records:  # a fresh start: the holds the file left out, checked once
        current = _with_better_holds(current, runs, likelihood, say)
    if records:
        current.record["added"] = records[-1]["added"]
        records[-1] = {**current.record, "candidates": [], "wall_time_s":
                       records[-1].get("wall_time_s")}
    else:
        records.append(current.record)
    return records, current


def _with_better_holds(current: Step, runs, likelihood, say) -> Step:
    """Step 0 held as its data say: where a heat input the file gave no hold fits clearly
    better piecewise constant (`fitting._hold_check`), the loop goes on from that hold
    (every later step would inherit the worse inputs), warns with what to write, and
    records the change on the step (`hold_changes`: column, hold, gain in log L)."""
    def refit(other):
        return evaluate(other, runs, likelihood).record["nll"]

    found = better_holds(current.spec, current.record["nll"], refit, say)
    if not found:
        return current
    spec = current.spec
    for f in found:
        spec = with_hold(spec, f.column, "zoh")
    better = evaluate(spec, runs, likelihood)  # again: the check's own fit kept no remarks
    for f in found:
        warnings.warn(f"{f.text} The investigation goes on from hold = \"zoh\" on "
                      f"{f.column}, which its models write.")
    better.record["hold_changes"] = [{"column": f.column, "hold": "zoh",
                                      "gain_log_l": round(f.gain, 3)} for f in found]
    return better


def _say_expected(loop: _Loop, records: list[dict]) -> None:
    """Before step `i` (> 0), what the last step cost, which this one, a model one effect
    larger scored against as many candidates, takes about as long or more: its wall time
    and its largest phase; where the effect it added made fits of the model dearer
    (`refit_cost_ratio` over `DEARER`), the time expected from that."""
    last = records[-2] if len(records) > 1 else None
    if last is None or not last.get("wall_time_s"):
        return
    phases = last.get("phase_times_s") or {}
    work = {k: v for k, v in phases.items() if k != COMPILATION}
    top = max(work, key=work.get, default=None)
    said = (f"step {len(records) - 1} starts; the last step took {last['wall_time_s']:.0f} s"
            + (f" ({top} {work[top]:.0f} s)" if top else ""))
    if loop.cost_ratio > DEARER:
        expect = expected_step_seconds(last, loop.cost_ratio)
        loop.say(f"{said}; a fit of the model it chose cost {loop.cost_ratio:.1f}× its "
                 f"average refit, and every refit of this step extends that model: expect "
                 f"about {duration_text(expect)} or more")
    else:
        loop.say(f"{said}: expect about as long or more (a model one effect larger, as "
                 "many candidates)")


def _say_forecast(loop: _Loop, current: Step, first: list[Candidate]) -> None:
    """Once scored, what the refits first in line will take where nonlinear models among
    them make it dearer than the last step's (`refit_forecast`)."""
    said = refit_forecast(loop.refit_costs, first, current.result.model.is_nonlinear)
    if said:
        loop.say(said)


def _stops_before(loop: _Loop, records: list[dict]) -> str | None:
    """Why the loop stops at its last step (`records[-1]`, said first): its residuals are
    white, or it is step `max_steps`; None to go on."""
    i = len(records) - 1
    rec = records[-1]
    loop.say(f"step {i}: −log L {rec['nll']:.1f}, RMSE " +
             ", ".join(f"{c} {v:.4g}" for c, v in rec["rmse"].items()))
    if all(p is not None and p > loop.white_p for p in rec["whiteness_p"].values()):
        return "residuals_white"
    if i >= loop.max_steps:
        return "max_steps"
    return None


def _step_candidates(loop: _Loop, current: Step, i: int) -> tuple:
    """`(candidates, chosen or None, MissingHeat or None)` of step `i`: its figures
    queued, its missing heat reconstructed beside the candidates' scoring and refits,
    the first supported candidate the held-out check keeps, else, where heat is missing,
    the heat network's proposal."""
    say, out = loop.say, loop.out
    _plot_ahead(loop.plots, out, i, current)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    missing = functools.cache(_beside(record_missing_heat, current, out, i, loop.white_p,
                                      say=say))
    cands = diagnose_step(current, loop.runs, loop.likelihood, refits=loop.refits,
                          fdr=loop.fdr, say=say, white_p=loop.white_p, initial=loop.spec,
                          missing=missing, search=loop.search,
                          forecast=lambda first: _say_forecast(loop, current, first))

    def checking(c):  # while a candidate's held-out folds are fitted
        _plot_ahead(loop.plots, out, i + 1, c.result, _added(c))
        if i + 1 < loop.max_steps:  # the step it would make is scored next
            score_ahead(c.result, loop.runs, loop.likelihood)

    with phase("held-out folds"):
        chosen = _choose(cands, current, loop.runs, loop.likelihood, loop.holdout_check, say,
                         loop.held_out, checking)
    with phase("missing heat (waited for)"):
        missing = missing()
    if chosen is None and loop.search is not None and missing is not None and \
            missing.carriers:
        with phase("refits"):
            chosen = _file_values_step(current, loop.runs, cands, loop.likelihood, loop.fdr,
                                       loop.white_p, loop.spec, loop.search,
                                       loop.holdout_check, say, loop.held_out)
    if chosen is None and loop.network and missing is not None and missing.carriers:
        with phase("heat network"):
            chosen = _network_step(current, loop.runs, missing, cands, loop.likelihood,
                                   loop.fdr, loop.white_p, loop.spec, loop.holdout_check, say,
                                   loop.held_out)
    if "symbolic_search" in current.record:
        record_evidence(current.record["symbolic_search"], cands)
    return cands, chosen, missing


def _record_candidates(rec: dict, cands: list[Candidate], chosen: Candidate | None,
                       t_step: float, phases: dict[str, float]) -> None:
    """The step's record gets its candidates, its wall time (since `t_step`) and where it
    went (`phase_times_s`, `_phase_times`) and, where the chosen candidate is tied, the
    advice that would separate the tie."""
    rec["candidates"] = [c.as_json() for c in cands]
    rec["wall_time_s"] = time.perf_counter() - t_step
    rec["phase_times_s"] = {k: round(v, 3) for k, v in phases.items()}
    if chosen is not None and chosen.tied_with:
        rec["separation"] = separation_advice({chosen.kind, *(k for k, _ in
                                                               chosen.tied_with)})


def _finish(loop: _Loop, records, stopped, advice, final: Step, steps_traces, heat_series,
            wall_time_s: float) -> dict:
    """The report (`report.json`'s dict), written with `out` beside the final model, the
    Markdown report and its figures."""
    report = _report(records, stopped, loop.likelihood, loop.fdr, loop.white_p, wall_time_s)
    report["noise"] = _noise(final)
    if advice:
        report["advice"] = advice
    if loop.out is not None:
        _write_outputs(loop.out, report, final, steps_traces, loop.runs, loop.plots,
                       heat_series)
    return json_safe(report)
