"""The results folder of `thermojax calibrate`: report.json, report.md,
model_calibrated.toml and plots (static polynomial, verification residual, the gyro
channels' Allan deviation); the observer folder is written by `verify`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ._pipeline import CalibrationResults

SCHEMA = 1


def _clean(x):
    """JSON-safe: NaN/inf -> None, arrays -> lists, tuples -> lists."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def calibration_report(res: CalibrationResults) -> dict:
    """The report as a dict (see docs/cli.md, `calibrate`)."""
    from .. import __version__

    c = res.config
    return _clean({
        "schema": SCHEMA, "thermojax_version": __version__, "config": str(c.path),
        "model": str(c.model), "channels": list(c.channels), "stages_run": list(c.stages),
        "temperature_sensor": c.temperature_sensor, "dt_s": c.dt_s,
        "stages": res.stages, "passed": res.passed,
        "calibrated_model": "model_calibrated.toml",
        "observer": "observer" if res.observer_dir is not None else None})


def _fmt(v, s=None):
    if v is None or not np.isfinite(v):
        return "—"
    return f"{v:.5g}" + ("" if s is None or not np.isfinite(s) else f" ± {s:.2g}")


def _interval(e) -> str:
    """`value [lower, upper]` of a report estimate dict, or —."""
    if e is None:
        return "—"
    return f"{e['value']:.4g} [{e['lower']:.4g}, {e['upper']:.4g}]"


def _allan_markdown(rows: list[dict]) -> list[str]:
    """The verification's Allan table: ARW and bias instability per run, gyro channel
    and output, with their confidence intervals."""
    if not rows:
        return []
    lines = ["", f"Overlapping Allan deviation of the gyro output on the held-back runs "
             f"(after skip_s, every {1 / rows[0]['sample_rate_hz']:g} s; intervals "
             f"{100 * rows[0]['ci']:.0f} %; `allan_<channel>.png`). Angle random walk "
             "N = σ(τ)·√τ where the slope is −1/2, bias instability B = min σ / 0.664 "
             "(≤: the minimum is at the longest τ, an upper bound).", "",
             "| run | channel | output | ARW, unit·√s | ARW, °/√h | τ, s | "
             "bias instability, unit | τ, s |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for out, o in r["outputs"].items():
            arw, bi = o["angle_random_walk"], o["bias_instability"]
            arw_tau = "—" if arw is None else f"{arw['tau_s']:g}"
            lines.append(
                f"| {r['run']} | {r['channel']} ({r['rate_unit']}) | {out} | {_interval(arw)} | "
                f"{_interval(o['angle_random_walk_deg_per_sqrt_h'])} | "
                f"{arw_tau} | "
                f"{'≤ ' if o['bias_instability_at_longest_tau'] else ''}{_interval(bi)} | "
                f"{bi['tau_s']:g} |")
    return lines


def report_markdown(res: CalibrationResults) -> str:
    c = res.config
    lines = [f"# Calibration of {', '.join(c.channels)}", "",
             f"Config `{c.path}`, model `{c.model}`; stages: {', '.join(c.stages)}.", ""]
    for st in res.stages:
        lines += [f"## {st['stage']}", "", st["did"] + ".", ""]
        if st["stage"] == "condition":
            lines += ["| run | use | samples | T log Hz | inertial log Hz | outliers |",
                      "|---|---|---|---|---|---|"]
            for name, r in st["runs"].items():
                lines.append(f"| {name} | {r['use']} | {r['samples']} | "
                             f"{r['temperature_rate_hz']:.3g} | {r['inertial_rate_hz']:.3g} | "
                             + ", ".join(f"{k} {v}" for k, v in r["outliers"].items()) + " |")
        elif st["stage"] == "static_polynomial":
            for ch, p in st["channels"].items():
                terms = ", ".join(f"c{k} = {_fmt(v, s)}" for k, (v, s)
                                  in enumerate(zip(p["coefficients"], p["std"])))
                lines.append(f"- **{ch}** (order {p['order']}, {len(p['plateaus'])} plateaus, "
                             f"Birge ratio {p['birge_ratio']:.3g}): {terms} "
                             f"(per K^k about 25 °C)")
        elif st["stage"] == "thermal_fit":
            rho = st.get("residual_autocorrelation") or {}
            lines += [f"{st['message']}, {st['n_steps']} steps, −log L {st['nll']:.2f}, "
                      f"{st['n_params']} parameters. The std assumes independent samples; "
                      "std with correlation is the Newey-West std, which holds when the "
                      "residuals are correlated in time (lag-1 autocorrelation: "
                      + ", ".join(f"{c} {v:.2f}" for c, v in rho.items()) + ").", "",
                      "| parameter | value | std | std with correlation |", "|---|---|---|---|"]
            for name, p in st["parameters"].items():
                if p.get("free", True):
                    lines.append(f"| {name} | {_fmt(p['value'])} | {_fmt(p['std'])} | "
                                 f"{_fmt(p.get('std_hac'))} |")
        elif st["stage"] == "coupling":
            lines += ["| channel | " + " | ".join(st["regressors"]) + " |",
                      "|---" * (len(st["regressors"]) + 1) + "|"]
            for i, ch in enumerate(st["channels"]):
                lines.append(f"| {ch} | " + " | ".join(
                    _fmt(st["matrix"][i][j], st["std"][i][j])
                    for j in range(len(st["regressors"]))) + " |")
        elif st["stage"] == "verify":
            lines += [f"Overall: **{'PASS' if st['passed'] else 'FAIL'}**.", "",
                      "| run | channel | RMS | peak | static-only RMS | spec | result |",
                      "|---|---|---|---|---|---|---|"]
            for k in st["checks"]:
                lines.append(f"| {k['run']} | {k['channel']} | {_fmt(k['rms'])} | "
                             f"{_fmt(k['peak'])} | {_fmt(k['static_polynomial_rms'])} | "
                             f"{k['spec']} | {'PASS' if k['passed'] else 'FAIL'} |")
            lines += _allan_markdown(st.get("allan") or [])
        lines.append("")
    return "\n".join(lines)


def plot_static(res: CalibrationResults, path: Path) -> Path:
    """Each channel's static polynomial against its plateau points."""
    from .._plots import column_unit, new_figure, style_figure

    chans = list(res.static)
    fig = new_figure(figsize=(11, 3.6 * len(chans)))
    for i, ch in enumerate(chans):
        p = res.static[ch]
        ax = fig.add_subplot(len(chans), 1, i + 1)
        T = np.array([q.temperature for _, q in p.plateaus])
        b = np.array([q.bias for _, q in p.plateaus])
        ax.errorbar(T, b, yerr=p.standard_error, fmt="o", label="dwell plateaus (mean ± s.e.)")
        grid = np.linspace(T.min() - 5, T.max() + 5, 200)
        ax.plot(grid, p.polynomial(grid), label=f"order-{p.polynomial.order} polynomial")
        ax.set_title(f"Static bias polynomial of {ch} from dwell plateaus")
        ax.set_xlabel(f"{res.config.temperature_sensor} (°C)")
        ax.set_ylabel(f"{ch}, {column_unit(ch, bias=True)}")
        ax.legend()
    fig.tight_layout()
    style_figure(fig)
    fig.savefig(path, dpi=100)
    return path


def plot_verification(res: CalibrationResults, path: Path) -> Path:
    """The residual bias (measured − observer) of each held-back run and channel."""
    from .._plots import column_unit, new_figure, style_figure

    chans = list(res.config.channels)
    fig = new_figure(figsize=(11, 3.6 * len(chans)))
    for i, ch in enumerate(chans):
        ax = fig.add_subplot(len(chans), 1, i + 1)
        for k in res.checks:
            if k.channel != ch:
                continue
            ax.plot((k.ts - k.ts[0]) / 3600.0, k.residual,
                    label=f"{k.run}: RMS {k.rms:.3g}, peak {k.peak:.3g}")
        lim = res.config.limits[ch]
        if "peak" in lim:
            for s in (-1, 1):
                ax.axhline(s * lim["peak"], color="red", linestyle="--",
                           label="peak limit" if s > 0 else None)
        ax.set_title(f"Residual bias of {ch} after the exported observer, held-back runs")
        ax.set_xlabel("time since the start of the run (h)")
        ax.set_ylabel(f"{ch}: measured − observer, {column_unit(ch, bias=True)}")
        ax.legend()
    fig.tight_layout()
    style_figure(fig)
    fig.savefig(path, dpi=100)
    return path


def plot_allan_curves(res: CalibrationResults, folder: Path) -> dict[str, Path]:
    """`allan_<channel>.png` per gyro channel of the verification: the raw,
    static-compensated and observer-compensated Allan deviation of each held-back run
    with its confidence band (`plot_allan`). Returns name -> path."""
    from ._plots import plot_allan

    out = {}
    for ch in dict.fromkeys(a.channel for a in res.allan or ()):
        rows = [a for a in res.allan if a.channel == ch]
        curves = {(label if len(rows) == 1 else f"{label}, {a.run}"): c
                  for a in rows for label, c in a.curves.items()}
        name = f"allan_{ch}.png"
        out[name] = plot_allan(folder / name, curves, rows[0].rate_unit,
                               f"{ch} on the held-back run{'s' if len(rows) > 1 else ''} "
                               f"{', '.join(a.run for a in rows)}")
    return out


def write_results(res: CalibrationResults, folder) -> dict[str, Path]:
    """Write report.json, report.md, model_calibrated.toml and the plots (with
    `allan_<channel>.png` per gyro channel verified) into `folder`
    (the observer folder is already there when `run_pipeline` was given
    `observer_dir=folder / "observer"`). Returns name -> path."""
    from ..model._model_file import save_model

    folder = Path(folder)
    out = {}
    report = calibration_report(res)
    out["report.json"] = folder / "report.json"
    out["report.json"].write_text(json.dumps(report, indent=1, allow_nan=False) + "\n",
                                  encoding="utf-8")
    out["report.md"] = folder / "report.md"
    out["report.md"].write_text(report_markdown(res), encoding="utf-8")
    out["model_calibrated.toml"] = folder / "model_calibrated.toml"
    save_model(res.calibrated_spec, out["model_calibrated.toml"],
               header=f"calibrated by thermojax calibrate from {res.config.path}")
    if res.static is not None:
        out["static_polynomial.png"] = plot_static(res, folder / "static_polynomial.png")
    if res.checks is not None:
        out["verification_residual.png"] = plot_verification(
            res, folder / "verification_residual.png")
    for name, path in plot_allan_curves(res, folder).items():
        out[name] = path
    return out
