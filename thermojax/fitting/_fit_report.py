"""A `FitResult` as files: `report.json` (docs/formats.md §5), the fitted model, the plots, a table."""

from __future__ import annotations

import json
from pathlib import Path

from ._summary import FitResult
from .._json import json_safe
from ..model._model_file import save_model


def fit_report(result: FitResult, runs: list[str]) -> dict:
    """The `report.json` of `thermojax fit`."""
    from .. import __version__

    return json_safe({
        "schema": 1,
        "thermojax_version": __version__,
        "likelihood": result.likelihood,
        "runs": runs,
        "rmse": result.rmse,
        "fit_percent": result.fit_percent,
        "nll": result.nll,
        "aic": result.aic,
        "bic": result.bic,
        "n_params": result.n_params,
        "n_samples": result.n_samples,
        "parameters": {k: {"value": v["value"], "std": v["std"], "free": v["free"]}
                       for k, v in result.parameters.items()},
        "correlation": {"names": result.free_names, "matrix": result.correlation},
        "identifiability": result.identifiability.to_json(),
        "per_run": result.per_run,
        "converged": result.converged,
        "message": result.message,
        "n_steps": result.n_steps,
        "wall_time_s": result.wall_time_s,
    })


def write_fit_outputs(result: FitResult, experiments, out: Path, runs: list[str],
                      profiles: dict | None = None) -> dict:
    """Write model.toml, report.json, one PNG per run and (Kalman) the smoothed node
    temperatures `smoothed_run<i>.csv` into `out`; return the report."""
    from .._plots import plot_fit
    from ..measurements._telemetry import write_telemetry

    out.mkdir(parents=True, exist_ok=True)
    save_model(result.spec, out / "model.toml",
               header=f"fitted by thermojax ({result.likelihood}) from {', '.join(runs)}")
    report = fit_report(result, runs)
    report.update(whiteness(result.spec.sensor_columns, experiments, result.predictions))
    if profiles:
        report["profile_intervals"] = json_safe(profiles)
    for r, (mean, std) in enumerate(result.smoothed):
        nodes = result.spec.node_names
        channels = {n: mean[:, i] for i, n in enumerate(nodes)}
        channels.update({f"{n}_std": std[:, i] for i, n in enumerate(nodes)})
        write_telemetry(out / f"smoothed_run{r}.csv", experiments[r].ts, channels,
                        comments=[f"RTS-smoothed node temperatures (°C) and stds, run {r}: "
                                  f"{runs[r]}"])
    (out / "report.json").write_text(json.dumps(report, indent=2))
    for r, (e, pred) in enumerate(zip(experiments, result.predictions)):
        plot_fit(out / f"fit_run{r}.png", e.ts, e.outputs, pred, result.spec.sensor_columns,
                 title=f"run {r}: {Path(e.name).name}")
    return report


def whiteness(columns, experiments, predictions) -> dict:
    """Ljung-Box p-value of each column's free-run residual, runs pooled."""
    from .._residual_analysis import ljung_box

    out, lags = {}, None
    for j, c in enumerate(columns):
        res = [e.outputs[:, j] - p[:, j] for e, p in zip(experiments, predictions)]
        _, p_value, lags = ljung_box(res)
        out[c] = p_value
    return json_safe({"whiteness_p": out, "whiteness_test": {
        "test": "Ljung-Box", "lags": lags, "residuals": "free-run (output error)",
        "pooling": "autocovariances summed over runs, each run about its own mean"}})


def comparison_table(result: FitResult) -> str:
    """Per-sensor RMSE and fit %, pooled and per run, as fixed-width text."""
    cols = list(result.rmse)
    lines = [f"{'sensor':<16}{'RMSE':>12}{'fit %':>10}" + "".join(
        f"{'run ' + str(r) + ' RMSE':>14}" for r in range(len(result.per_run)))]
    for c in cols:
        row = f"{c:<16}{result.rmse[c]:>12.4g}{result.fit_percent[c]:>10.2f}"
        row += "".join(f"{pr['rmse'][c]:>14.4g}" for pr in result.per_run)
        lines.append(row)
    lines.append(f"-log L = {result.nll:.3f}   AIC = {result.aic:.3f}   BIC = {result.bic:.3f}   "
                 f"n_params = {result.n_params}   ({result.message})")
    for msg in result.identifiability.messages:
        lines.append(f"unidentifiable: {msg}")
    return "\n".join(lines)
