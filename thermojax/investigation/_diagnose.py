"""`thermojax diagnose`: how a model fails, and which effects would fix it (unchanged model)."""

from __future__ import annotations

import json
from pathlib import Path

from ._diagnostic_plots import PLOT_KEYS
from ._diagnostics import diagnose_traces, slowest_time_constant
from ._diagnose_step import diagnose_step
from ._held_out import N_BLOCKS, HeldOutFits, check_holdout
from ._missing_heat_step import record_missing_heat, record_unexplained
from ._outputs import _noise, _version
from ._step import evaluate
from ._selection import held_out_advice, significance_rule
from .._json import json_safe
from .._plots import column_units
from ..model._spec import ModelSpec


def diagnose(spec: ModelSpec, runs, *, likelihood: str = "output_error", out: Path | None = None,
             refits: int = 3, fdr: float = 0.05, progress=None) -> dict:
    """Fit `spec`, describe its residuals and rank every candidate effect.

    Returns the `report.json` dict: the fit's figures (`rmse`, `fit_percent`, `nll`,
    `aic`, `bic`, `n_params`, `whiteness_p`), `candidates` ranked best first (as in
    `investigate`), and `diagnostics` (residuals by run and chamber phase,
    autocorrelation, cross-correlation with every input and its derivative, the
    cumulated periodogram, and plain-English findings). With `out`, writes it with
    `report.md` and the plots.
    """
    say = progress or (lambda _m: None)
    step = evaluate(spec, runs, likelihood)
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
    missing = record_missing_heat(step, out, 0, 0.01, say)
    cands = diagnose_step(step, runs, likelihood, refits=refits, fdr=fdr, say=say,
                          initial=spec)
    fits = HeldOutFits()  # the same rule as `investigate`: every supported one checked
    for c in cands:
        if c.supported:
            try:
                check_holdout(c, step, runs, likelihood, say, fits)
            except Exception as err:  # the check could not run: say so, keep the verdict
                c.add_note(f"held-out check could not run: {type(err).__name__}: {err}"[:200],
                           first=True)
    advice = None
    if not any(c.supported for c in cands):
        record_unexplained(step, missing, say)
        advice = held_out_advice(cands, likelihood)  # as `investigate` stops
    columns = list(spec.sensor_columns) + [b.column for b in spec.biases]
    inputs = list(spec.input_columns)
    boundary = list(spec.boundary_columns)
    rec = step.record
    units = column_units(spec.sensor_columns, [b.column for b in spec.biases])
    time_scale = slowest_time_constant(rec.get("parameters") or {})
    report = {
        "schema": 1, "thermojax_version": _version(), "likelihood": likelihood,
        **{k: rec[k] for k in ("rmse", "fit_percent", "nll", "aic", "bic", "n_params",
                               "whiteness_p", "whiteness_lags", "parameters")},
        "candidates": [c.as_json() for c in cands],
        "diagnostics": diagnose_traces(columns, step.traces, inputs, boundary, units=units,
                                       time_scale=time_scale),
        "noise": _noise(step),
        "significance_rule": significance_rule(fdr, N_BLOCKS),
        **{k: rec[k] for k in ("missing_heat", "unexplained") if k in rec},
        **({"advice": advice} if advice else {}),
    }
    report = json_safe(report)
    if out is not None:
        from ._investigation_report import write_investigation_report

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        story = {"steps": [{**rec, "candidates": report["candidates"]}],
                 "stopped_because": "diagnosis only", "likelihood": likelihood,
                 "noise": report["noise"], "significance_rule": report["significance_rule"],
                 **({"advice": advice} if advice else {})}
        # report.md and every plot, each written once (`diagnose_<key>.png`)
        from ._missing_heat_plots import nearest_sensors

        write_investigation_report(out, json_safe(story), [step.traces], columns, inputs,
                                   boundary, diagnosis=True, units=units,
                                   missing_heat=[missing], nearest=nearest_sensors(spec),
                                   input_units={h.input: "W" for h in spec.heat_inputs})
        report["plots"] = {k: f"diagnose_{k}.png" for k in PLOT_KEYS}
        if (out / "diagnose_missing_heat.png").is_file():
            report["plots"]["missing_heat"] = "diagnose_missing_heat.png"
        (out / "report.json").write_text(json.dumps(report, indent=2, allow_nan=False))
    return report
