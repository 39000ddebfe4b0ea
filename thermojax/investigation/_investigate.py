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

import time
from pathlib import Path

from ._background import _beside, score_ahead
from ._candidates import Candidate
from ._checkpoint import _clear_earlier_run, _inputs, _load_checkpoint, _save_checkpoint
from ._diagnose_step import diagnose_step
from ._held_out import HeldOutFits, _choose
from ._missing_heat_step import _network_step, record_missing_heat, record_unexplained
from ._outputs import _noise, _plot_ahead, _report, _write_outputs
from ._plots_ahead import PlotsAhead
from ._refit_verdicts import added_effect
from ._selection import held_out_advice
from ._separation import separation_advice
from ._step import Step, confirmed_optimum, evaluate
from .._blas_threads import one_blas_thread
from .._json import json_safe
from .._memory import release_compiled_if_crowded
from ..measurements._telemetry import Telemetry
from ..model._spec import ModelSpec


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

