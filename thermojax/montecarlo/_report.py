"""The Monte Carlo report: report.json, report.md and distribution plots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._summary import PERCENTILES, summarize  # noqa: F401


def write_report(out: Path, config, results: dict, names, study, atomic_write) -> dict:
    from .. import __version__
    from .._json import json_safe

    unit = study.bias.column
    bias_units = "deg/h" if unit.endswith("_dph") else ("ug" if unit.endswith("_ug") else
                                                        "channel units")
    summary = summarize(results, names, results["log_deviation"], config.bias_limit,
                        bias_units)
    report = {"schema": 1, "thermojax_version": __version__, "config": str(config.path),
              "model": str(config.model_path), "bias_channel": unit,
              "temperature_node": study.network.topology.node_names[study.bias.temperature],
              "population": config.population.describe(), "profile": config.profile,
              "n_units": config.n_units, "chunk_size": config.chunk_size, "seed": config.seed,
              "calibration_profile": study.calibration, "fit_settings": config.fit,
              "batch_model_log_deviation": (None if study.batch_logdev is None else
                                            dict(zip(names, study.batch_logdev.tolist()))),
              **summary}
    report = json_safe(report)
    atomic_write(out / "report.json", (json.dumps(report, indent=1) + "\n").encode())
    atomic_write(out / "report.md", _markdown(report).encode())
    plots = _plots(out, results, report, atomic_write)
    report["plots"] = plots
    return report


def _markdown(r: dict) -> str:
    u = r["bias_units"]
    pop = r["population"]
    lines = [f"# Unit-variance Monte Carlo: {r['n_units']} units", "",
             f"Model `{r['model']}`, bias channel `{r['bias_channel']}` (its node "
             f"`{r['temperature_node']}`); population: "
             + (f"preset `{pop['preset']}` ({pop['preset_source']}); " if pop["preset"] else "")
             + f"{len(pop['spreads'])} parameters vary lognormally (mean nominal, spread = "
             f"relative std), {len(pop['voids'])} void entries. Profile: "
             f"{r['profile']['lo']:g}..{r['profile']['hi']:g} °C at {r['profile']['rate']:g} "
             f"°C/min, {r['profile']['dwell']:g} s dwells, {r['profile']['dt']:g} s samples, "
             f"{r['profile']['power']:g} W.", "",
             "Methods: **nominal** = the nominal model's steady-state Kalman observer and the "
             "bias model on its estimates (batch-level default matrices); **batch** = the "
             "same with one model fitted to the pooled calibration runs of a sample of units; "
             "**fitted** = each unit identified from its own calibration run (MAP "
             "output-error fit, the population as prior) and compensated with its fitted "
             "model; **own** = the unit's own true model (the ideal per-unit calibration "
             "bound)" + ("; **trim_step**, **trim_sweep** = the nominal model with one factor "
                         "on every capacitance and one on every conductance, fitted to the "
                         "unit's end-of-line power step or two-tone sweep"
                         if "trim_step" in r["methods"] else "") + ".", "",
             "Secondary-state offset: the estimated bias-node temperature's mean error over "
             "the test run's last tenth (its final dwell); step overshoot: its largest excess "
             "over the true trajectory after a 20 K chamber step, % of the step; phase loss: "
             "its phase against the truth for a 300 s chamber sinusoid (degrees).", "",
             f"| method | within ±{r['bias_limit']:g} {u} (peak) | bias peak p50 / p95 / p99 / "
             f"max ({u}) | temperature peak p50 / p95 / max (K) | offset p50 / p95 (mK) | "
             "step overshoot p50 / p95 (%) | phase loss p50 / p95 (°) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for m in r["methods"]:
        b, t = r["percentiles"][m]["bias_peak"], r["percentiles"][m]["temp_peak"]
        o, s_ = r["percentiles"][m]["temp_offset"], r["percentiles"][m]["step_overshoot"]
        ph = r["percentiles"][m]["phase_loss"]
        lines.append(f"| {m} | {100 * r['fraction_within_bias_spec'][m]:.1f} % | "
                     f"{b['p50']:.3g} / {b['p95']:.3g} / {b['p99']:.3g} / {b['max']:.3g} | "
                     f"{t['p50']:.3g} / {t['p95']:.3g} / {t['max']:.3g} | "
                     f"{1e3 * o['p50']:.3g} / {1e3 * o['p95']:.3g} | "
                     f"{s_['p50']:.3g} / {s_['p95']:.3g} | {ph['p50']:.3g} / {ph['p95']:.3g} |")
    lines += ["", "## Which spread matters most (nominal method, peak bias error)", "",
              "Least-squares coefficients of the peak bias error on the standardized "
              "log-deviations (change per standard deviation of the parameter), and each "
              "parameter's correlation with the error:", "",
              f"| rank | parameter | {u} per sd | correlation |", "|---:|---|---:|---:|"]
    for i, s in enumerate(r["sensitivity"][:10]):
        lines.append(f"| {i + 1} | `{s['parameter']}` | {s['coefficient_per_sd']:+.3g} | "
                     f"{s['correlation']:+.2f} |")
    if "fit" in r:
        lines += ["", "## The per-unit fits", "",
                  f"Median RMS of the calibration residuals {r['fit']['fit_rms_median']:.3f} "
                  "noise stds (1 = fitted to the noise). Log-parameter errors (fitted minus "
                  "true) against the population's spread and the fits' posterior stds; "
                  "z = error / posterior std (about 1 where the std is honest):", "",
                  "| parameter | population std | error RMS | posterior std (median) | z RMS |",
                  "|---|---:|---:|---:|---:|"]
        for p in r["fit"]["parameters"]:
            lines.append(f"| `{p['parameter']}` | {p['prior_std']:.3g} | {p['error_rms']:.3g} "
                         f"| {p['posterior_std_median']:.3g} | {p['z_rms']:.2f} |")
    lines.append("")
    return "\n".join(lines)


def _plots(out: Path, results: dict, r: dict, atomic_write) -> list[str]:
    """Per-unit peak-error histograms, one outline per compensation method."""
    from .._plots import new_figure, save_figure

    files = []
    for key, title, unit in (("bias_peak", "Peak bias error per unit", r["bias_units"]),
                             ("temp_peak", f"Peak error of the estimated {r['temperature_node']} "
                              "temperature per unit", "K")):
        fig = new_figure(figsize=(12, 6))
        ax = fig.add_subplot(1, 1, 1)
        values = {m: np.maximum(results[f"{m}_{key}"], 1e-12) for m in r["methods"]}
        lo = min(float(v.min()) for v in values.values())
        hi = max(float(v.max()) for v in values.values())
        bins = np.logspace(np.log10(lo) - 0.05, np.log10(hi) + 0.05, 40)   # shared bins
        for m, label in r["methods"].items():
            # outlines, not translucent fills: overlaps keep each method's own colour,
            # the one its legend entry shows
            ax.hist(values[m], bins=bins, histtype="step", lw=1.8, label=label)
        if key == "bias_peak":
            ax.axvline(r["bias_limit"], color="k", ls="--",
                       label=f"specification {r['bias_limit']:g} {unit}")
        ax.set_xscale("log")
        ax.set_xlabel(f"peak error over the profile ({unit})")
        ax.set_ylabel("number of units")
        ax.set_title(f"{title}: {r['n_units']} units, by compensation method")
        ax.legend()
        name = f"{key}_distribution.png"
        tmp = out / f".{name}.tmp.png"
        save_figure(fig, tmp)
        atomic_write(out / name, tmp.read_bytes())
        tmp.unlink()
        files.append(name)

    return files
