"""A `FitResult` as files: `report.json` (docs/formats.md §5), the fitted model, the plots, a table."""

from __future__ import annotations

import json
import math
from pathlib import Path

from ._interval_check import interval_lines, wald_interval
from ._interval_check import is_log_parameter as _is_log_parameter
from ._summary import FitResult
from .._plots import column_unit
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
        "parameters": {k: {"value": v["value"], "std": v["std"], "free": v["free"],
                           **({"at_bound": True} if v.get("at_bound") else {})}
                       for k, v in result.parameters.items()},
        "correlation": {"names": result.free_names, "matrix": result.correlation},
        "identifiability": result.identifiability.to_json(),
        "per_run": result.per_run,
        "converged": result.converged,
        "message": result.message,
        "dominant_samples": [d.to_json() for d in result.dominant],
        "n_steps": result.n_steps,
        "method": result.method,
        "wall_time_s": result.wall_time_s,
        # ETD2 steps per sample period the fit integrated nonlinear effects with
        "etd2_substeps": result.model.etd2_substeps if result.model.is_nonlinear else None,
    })


def write_fit_outputs(result: FitResult, experiments, out: Path, runs: list[str],
                      profiles: dict | None = None, initial=None,
                      dropped: list[dict] | None = None,
                      warnings: list[str] | None = None) -> dict:
    """Write model.toml, report.json, report.md, one PNG per run and (Kalman) the smoothed
    node temperatures `smoothed_run<i>.csv` into `out`; return the report.

    `initial`: the model as given (its file values flag parameters "at bound" and say
    whether a sensor's noise was given or estimated). `dropped`: the cells `--outliers drop`
    left out, one dict each (`dropped_cells`). `warnings`: what the command warned of while
    fitting (`warnings`, also shown at the top of report.md)."""
    from .._plots import plot_fit
    from ..measurements._telemetry import write_telemetry

    out.mkdir(parents=True, exist_ok=True)
    save_model(result.spec, out / "model.toml",
               header=f"fitted by thermojax ({result.likelihood}) from {', '.join(runs)}")
    report = fit_report(result, runs)
    report.update(whiteness(result.spec.sensor_columns, experiments, result.predictions))
    report["dropped_cells"] = json_safe(dropped or [])
    report["warnings"] = list(warnings or [])
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
    plots = []
    for r, (e, pred) in enumerate(zip(experiments, result.predictions)):
        plots.append(f"fit_run{r}.png")
        plot_fit(out / plots[-1], e.ts, e.outputs, pred, result.spec.sensor_columns,
                 title=f"Measured and fitted model, run {r} ({Path(e.name).name})")
    rows = parameter_rows(report, file_values(initial))
    write_fit_markdown(out, report, rows, plots, _noise_given(initial))
    return report


def file_values(spec) -> dict:
    if spec is None:
        return {}
    from ..model import spec_parameters

    return {k: float(p.value) for k, p in spec_parameters(spec).items() if p is not None}


def _noise_given(spec) -> dict:
    """column -> (std, fixed) of each sensor's noise in the model file."""
    if spec is None:
        return {}
    return {s.column: (float(s.noise.value), bool(s.noise.fixed)) for s in spec.sensors
            if s.noise is not None}


def whiteness(columns, experiments, predictions) -> dict:
    """Ljung-Box p-value of each column's free-run residual, runs pooled."""
    from ._residual_analysis import ljung_box

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


# ---------------------------------------------------------------------------
# The parameter table (screen and report.md)

_EFFECT_UNITS = {"coefficient": "W/K⁴", "alpha": "1/K", "beta": "1/K", "offset": "°C",
                 "gain": "1", "time_constant": "s", "tau": "s", "capacitance": "J/K",
                 "conductance": "W/K", "conductance_b": "W/K"}
_AT_BOUND = 1e-6  # a positive parameter below this fraction of its file value


def parameter_unit(name: str, column_units: dict | None = None) -> str:
    """The unit of a parameter by its dotted name (docs/formats.md §2): J/K, W/K, °C, ...

    `column_units`: column -> unit, overriding `column_unit` (a bias channel's unit
    from its name: `_dph` deg/h, `_ug` µg)."""
    parts = name.split(".")
    last = parts[-1]
    units = column_units or {}

    def unit_of(column, bias):
        return units.get(column) or column_unit(column, bias)

    if parts[0] == "effects" and len(parts) >= 3:
        kind = parts[1]
        if kind == "conductance_input" and last == "coefficient":
            return "1/unit"  # per unit of the modulating input
        if kind == "heat_source" and last == "gain":
            return "W/W"
        if kind == "viscoelastic" and last == "k":
            column = parts[2].split("-")[-1] if len(parts) > 3 else None
            return f"{unit_of(column, True)}/K"
        return _EFFECT_UNITS.get(last, "")
    if parts[0] == "biases" and len(parts) >= 3 and last != "noise":
        u, term = unit_of(parts[1], True), parts[2]  # _bias.BiasFit.names
        if term.startswith("poly") and term[4:].isdigit():
            p = int(term[4:])
            return u if p == 0 else f"{u}/°C" if p == 1 else f"{u}/°C^{p}"
        return {"gradient": f"{u}/K", "rate": f"{u}/(K/s)"}.get(term, u)
    if last == "capacitance":
        return "J/K"
    if last == "conductance":
        return "W/K"
    if last == "gain":
        return "W/W" if parts[0] == "heat_inputs" else "1"
    if last == "noise":
        return unit_of(parts[1], parts[0] == "biases") if parts[0] in ("sensors", "biases") \
            else "°C"
    if last == "process_noise":
        return "°C/√s"
    if last == "initial":
        return "°C"
    if last == "time_constant":
        return "s"
    return ""




def parameter_rows(report: dict, initial: dict | None = None,
                   column_units: dict | None = None) -> list[dict]:
    """One row per parameter of a fit `report` (`report.json`): `name`, `value`, `std`,
    `lower`, `upper` (95 %), `interval` ("profile", "Wald" or "Wald, log scale"; None
    without a std), `unit` and `flags` (a list of "fixed", "unidentifiable", "at bound").

    The interval is the profile-likelihood one where `report["profile_intervals"]` has
    it; else Wald: value ± 1.96 std, or for a positive (log-parameterized) parameter
    exp(log v ± 1.96 std / v). `initial`: dotted name -> file value, for "at bound" (a
    positive parameter driven below 1e-6 of its file value)."""
    profiles = report.get("profile_intervals") or {}
    initial = initial or {}
    rows = []
    for name, p in (report.get("parameters") or {}).items():
        v, sd, free = p.get("value"), p.get("std"), p.get("free", True)
        flags, lo, hi, how = [], None, None, None
        if not free:
            flags.append("fixed")
        elif p.get("at_bound"):   # held at its zero boundary: known, not unidentifiable
            flags.append("at bound")
        elif sd is None:
            flags.append("unidentifiable")
        elif sd == 0:  # no certainty: a std of zero is never printed
            sd = None
            flags.append("std undetermined (no curvature along it)")
        log = _is_log_parameter(name)
        v0 = initial.get(name)
        if free and log and v is not None and v0 and v0 > 0 and v < _AT_BOUND * v0 \
                and "at bound" not in flags:
            flags.append("at bound")
        prof = profiles.get(name)
        if prof and prof.get("lower") is not None and prof.get("upper") is not None:
            lo, hi, how = float(prof["lower"]), float(prof["upper"]), "profile"
        elif free and sd is not None and v is not None and math.isfinite(sd):
            (lo, hi), how = wald_interval(name, v, sd)
        rows.append({"name": name, "value": v, "std": sd, "lower": lo, "upper": hi,
                     "interval": how, "unit": parameter_unit(name, column_units),
                     "flags": flags})
    return rows


def _g(x, fmt: str = ".4g") -> str:
    return "–" if x is None or not math.isfinite(float(x)) else f"{float(x):{fmt}}"


def _p(x) -> str:
    if x is None:
        return "–"
    return "< 1e-300" if float(x) < 1e-300 else f"{float(x):.2g}"


def _interval_text(r: dict) -> str:
    if r["lower"] is None:
        return "–"
    mark = {"profile": " (P)", "Wald": " (W)", "Wald, log scale": " (Wl)"}[r["interval"]]
    return f"[{_g(r['lower'])}, {_g(r['upper'])}]{mark}"


_INTERVAL_LEGEND = ("95 % interval: (P) profile likelihood; (W) Wald, value ± 1.96 std; "
                    "(Wl) Wald on the log scale, exp(log value ± 1.96 std/value), for "
                    "positive parameters.")


def format_parameter_table(rows: list[dict]) -> str:
    """The parameter table as fixed-width text, for the screen."""
    w = max([9] + [len(r["name"]) for r in rows]) + 2
    lines = [f"{'parameter':<{w}}{'value':>12}{'std':>11}  {'95 % interval':<30}"
             f"{'unit':<8}flags"]
    for r in rows:
        lines.append(f"{r['name']:<{w}}{_g(r['value']):>12}{_g(r['std'], '.2g'):>11}  "
                     f"{_interval_text(r):<30}{r['unit']:<8}{', '.join(r['flags'])}")
    lines.append(_INTERVAL_LEGEND)
    return "\n".join(lines)


def _md_parameter_table(rows: list[dict]) -> list[str]:
    md = ["| parameter | value | std | 95 % interval | interval | unit | flags |",
          "|---|---:|---:|---|---|---|---|"]
    for r in rows:
        iv = "–" if r["lower"] is None else f"[{_g(r['lower'])}, {_g(r['upper'])}]"
        md.append(f"| {r['name']} | {_g(r['value'])} | {_g(r['std'], '.2g')} | {iv} | "
                  f"{r['interval'] or '–'} | {r['unit']} | {', '.join(r['flags']) or '–'} |")
    return md


def write_fit_markdown(out: Path, report: dict, rows: list[dict], plots: list[str],
                       noise_given: dict | None = None) -> Path:
    """`report.md` of `thermojax fit`: the fit in numbers, the parameter table, the error
    per sensor and run, whiteness, identifiability and the plots (`plots`: file names in
    `out`, one per run). `noise_given`: column -> (std, fixed) from the model file."""
    runs = report.get("runs") or []
    md = ["# Fit report", "",
          f"Likelihood `{report.get('likelihood')}`, {len(runs)} run(s): "
          + ", ".join(f"`{Path(r).name}`" for r in runs) + ".",
          f"−log L = {_g(report.get('nll'))}, AIC = {_g(report.get('aic'))}, "
          f"BIC = {_g(report.get('bic'))}, {report.get('n_params')} free parameters, "
          f"{report.get('n_samples')} samples; "
          + ("converged" if report.get("converged") else "**not converged**")
          + (f" ({report.get('message')})" if report.get("message") not in
             (None, "converged") else "") + "."
          + (f" Nonlinear effects integrated in {report['etd2_substeps']} "
             + ("fourth-order exponential (ETDRK4)" if report.get("likelihood") == "kalman"
                else "ETD2") + " step(s) per sample period."
             if report.get("etd2_substeps") else "")
          + (f" Solved by {report['method']}." if report.get("method") else ""), ""]
    md += [f"**Warning:** {w}" for w in report.get("warnings") or []]
    md += ([""] if report.get("warnings") else []) + ["## Parameters", ""]
    md += _md_parameter_table(rows) + [
        "", "95 % interval: profile likelihood where computed (`--profile`, and the "
        "automatic check where the curvature is weak or the model has a near-null "
        "direction); else Wald, "
        "value ± 1.96 std, taken on the log scale, exp(log value ± 1.96 std/value), for "
        "positive parameters. Flags: fixed (given in the model file), unidentifiable (no "
        "std: the data do not determine it), at bound (a positive parameter driven to "
        "~0, or a Kalman fit's process noise whose optimum is its zero boundary: held "
        "there, known, no std).", ""]
    ident = report.get("identifiability") or {}
    for d in ident.get("unidentifiable") or []:
        if d.get("message"):
            md.append(f"- unidentifiable: {d['message']}")
    md += interval_lines({k: v for k, v in (report.get("profile_intervals") or {}).items()
                          if "agrees" in v})
    md += ["", "## Error per sensor", "",
           "Noise: the sensor's std from the model file when fixed there (a yardstick for "
           "the error); when estimated, the fit's own estimate (RMSE / noise ≈ 1 then holds "
           "by construction and says nothing about success).", ""]
    per_run = report.get("per_run") or []
    head = ["sensor", "RMSE, °C", "fit %", "noise, °C", "noise is", "whiteness p"] + [
        f"run {r} RMSE" for r in range(len(per_run))]
    md += ["| " + " | ".join(head) + " |", "|---|" + "---:|" * 3 + "---|---:|"
           + "---:|" * len(per_run)]
    params = report.get("parameters") or {}
    for c, v in (report.get("rmse") or {}).items():
        p = params.get(f"sensors.{c}.noise") or {}
        given = (noise_given or {}).get(c)
        kind = "–" if not p else ("given (fixed)" if not p.get("free", True) else "estimated")
        if given is not None and not p:
            kind = "given (fixed)" if given[1] else "model file value"
        noise = p.get("value") if p else (given[0] if given else None)
        row = [c, _g(v), _g((report.get("fit_percent") or {}).get(c), ".2f"), _g(noise), kind,
               _p((report.get("whiteness_p") or {}).get(c))]
        row += [_g((pr.get("rmse") or {}).get(c)) for pr in per_run]
        md.append("| " + " | ".join(str(x) for x in row) + " |")
    md += ["", "Whiteness: Ljung-Box test of the free-run residual, runs pooled; p below "
           "0.05 says the residual still has structure the model does not explain.", "",
           "## Measured against model", ""]
    for r, name in enumerate(plots):
        md += [f"Run {r}" + (f" (`{Path(runs[r]).name}`)" if r < len(runs) else "") + ":", "",
               f"![measured against model, run {r}]({name})", ""]
    path = out / "report.md"
    path.write_text("\n".join(md) + "\n", encoding="utf-8")
    return path
