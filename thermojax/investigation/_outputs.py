"""What an investigation writes: the `report.json` dict (`_report`, `_noise`), the final
model, the Markdown report and its figures (`_write_outputs`), and each step's figures
queued ahead as the loop goes (`_plot_ahead`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._held_out import N_BLOCKS
from ._missing_heat_step import _unexplained
from ._plots_ahead import PlotsAhead
from ._selection import significance_rule
from ._step import Step
from .._json import json_safe
from ..model._model_file import save_model
from ..model._spec import ModelSpec


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
