"""How a model fails, drawn: the diagnostic PNGs of its run traces and the error per
step of an investigation.

NumPy and matplotlib (no JAX, no pyplot: figures come from `_plots.new_figure`, so
the user's matplotlib backend is left alone). Run traces and the statistics are
those of `_diagnostics`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._plots import new_figure
from .._residual_analysis import (PHASES, cross_correlation, cumulated_periodogram,
                                 pooled_autocorrelation, residuals_by_phase)
from ._diagnostics import _check_runs, _dt, _label, _max_lag, _phases, _signals, _split_inputs

_DPI = 80


def _stride(n: int, points: int = 1500) -> int:
    return max(1, n // points)


def _save(fig, path: Path) -> None:
    """Write `fig` with fixed margins (tight_layout costs as much as drawing it)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=min(1.0 / w, 0.3), right=1 - min(0.2 / w, 0.1),
                        bottom=min(0.6 / h, 0.3), top=1 - min(0.35 / h, 0.15),
                        hspace=0.45, wspace=0.3)
    fig.savefig(path, dpi=_DPI)


def _fit_figure(columns, runs, res):
    """Rows: (column, residual) pairs; one column of panels per run; time in h."""
    p, nr = len(columns), len(runs)
    fig = new_figure(figsize=(min(4.0 * nr, 16.0), 2.6 * p + 0.6))
    axes = fig.subplots(2 * p, nr, squeeze=False, gridspec_kw={"height_ratios": [2, 1] * p})
    for i, r in enumerate(runs):
        t_h = r["ts"] / 3600.0
        s = _stride(len(t_h))
        for j, c in enumerate(columns):
            ax = axes[2 * j, i]
            ax.plot(t_h[::s], r["measured"][::s, j], ".", ms=2, color="0.4", label="measured")
            ax.plot(t_h[::s], r["predicted"][::s, j], color="tab:blue", lw=1.0, label="model")
            if i == 0:
                ax.set_ylabel(c)
            if j == 0:
                ax.set_title(r["name"], fontsize=9)
            if i == 0 and j == 0:
                ax.legend(fontsize=7, loc="best")
            ax = axes[2 * j + 1, i]
            ax.plot(t_h[::s], res[j][i][::s], color="tab:red", lw=0.6)
            ax.axhline(0, color="k", lw=0.5)
            if i == 0:
                ax.set_ylabel("residual", fontsize=8)
        axes[-1, i].set_xlabel("time, h")
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    return fig


def _acf_figure(columns, res, dt: float, shortest: int):
    """Pooled residual autocorrelation per column, lags in s, with the ±1.96/√N band."""
    p = len(columns)
    acf_lags = max(1, min(50, shortest - 1))
    fig = new_figure(figsize=(6, 1.9 * p + 0.4))
    axes = fig.subplots(p, 1, squeeze=False)
    for j, c in enumerate(columns):
        ax = axes[j, 0]
        rho, n = pooled_autocorrelation(res[j], acf_lags)
        k = np.arange(1, acf_lags + 1)
        ax.vlines(k * dt, 0, rho, color="tab:blue")
        band = 1.96 / math.sqrt(max(n, 1))
        ax.axhspan(-band, band, color="0.85")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(f"{c}\nACF", fontsize=8)
    axes[-1, 0].set_xlabel("lag, s")
    axes[0, 0].set_title("pooled residual autocorrelation (grey: ±1.96/√N)", fontsize=9)
    return fig


def _xcorr_figure(columns, runs, res, input_names, dt: float, lag: int):
    """One panel per column: its residual against every input and derivative, 95 % band."""
    p = len(columns)
    signals = [_signals(r, input_names) for r in runs]
    fig = new_figure(figsize=(7, 2.2 * p + 0.6))
    axes = fig.subplots(p, 1, squeeze=False)
    for j, c in enumerate(columns):
        ax = axes[j, 0]
        band = None
        for s in range(2 * len(input_names)):
            name, deriv, _ = signals[0][s]
            lags, ccf, band = cross_correlation(res[j], [sg[s][2] for sg in signals], lag)
            ax.plot(lags * dt, ccf, lw=1.0, ls="--" if deriv else "-", label=_label(name, deriv))
        if band is not None:
            ax.axhspan(-band, band, color="0.85")
            ax.legend(fontsize=6, ncol=2, loc="best")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(f"{c}\ncorrelation", fontsize=8)
    axes[-1, 0].set_xlabel("lag, s (positive: input leads)")
    axes[0, 0].set_title("residual vs inputs and their derivatives (grey: 95 % band)", fontsize=9)
    return fig


def _periodogram_figure(columns, res):
    """Cumulated periodogram per column with the 5 % Kolmogorov-Smirnov band."""
    p = len(columns)
    fig = new_figure(figsize=(min(3.2 * p, 16.0), 3.0))
    axes = fig.subplots(1, p, squeeze=False)
    for j, c in enumerate(columns):
        ax = axes[0, j]
        if any(np.isfinite(x).sum() >= 4 for x in res[j]):
            f, cp, bound = cumulated_periodogram(res[j])
            ax.plot(f, cp, color="tab:blue", lw=1.0)
            ax.plot([0, 1], [0, 1], color="k", lw=0.5)
            ax.fill_between(f, f - bound, f + bound, color="0.85")
        ax.set_title(c, fontsize=9)
        ax.set_xlabel("frequency / Nyquist", fontsize=8)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.05)
    axes[0, 0].set_ylabel("cumulated periodogram")
    return fig


def _phases_figure(columns, runs, res, input_names, boundary_inputs):
    """Grouped bars: mean residual per chamber phase and column."""
    p = len(columns)
    chamber, powers = _split_inputs(input_names, boundary_inputs)
    ph = [_phases(r, input_names, chamber, powers) for r in runs]
    fig = new_figure(figsize=(6, 3))
    ax = fig.subplots()
    width = 0.8 / max(p, 1)
    x = np.arange(len(PHASES))
    for j, c in enumerate(columns):
        by = residuals_by_phase(res[j], ph)
        means = [by[k]["mean"] if by[k]["mean"] is not None else 0.0 for k in PHASES]
        ax.bar(x + (j - (p - 1) / 2) * width, means, width, label=c)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(x)
    ax.set_xticklabels([k.replace("_", " ") for k in PHASES], fontsize=8)
    ax.set_ylabel("mean residual")
    ax.legend(fontsize=7)
    ax.set_title("residual by chamber phase", fontsize=9)
    return fig


def diagnostic_plots(out_dir, prefix: str, columns, runs, input_names, boundary_inputs=(),
                     max_lag: int | None = None) -> dict[str, str]:
    """Write the diagnostic PNGs into `out_dir`; return their file names (relative to
    `out_dir`, `<prefix>_<key>.png`) by key:

    - `fit`: per column, measured against model over time for each run, residual below;
    - `acf`: pooled residual autocorrelation with the ±1.96/√N band, per column;
    - `xcorr`: cross-correlation of the residual with each input and derivative, bands;
    - `periodogram`: cumulated periodogram with the 5 % Kolmogorov-Smirnov band;
    - `phases`: residual mean per chamber phase, per column.

    Arguments as `diagnose_traces` takes them (`max_lag` in samples).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = _check_runs(columns, runs, input_names)
    pre = f"{prefix}_" if prefix else ""
    names = {k: f"{pre}{k}.png" for k in ("fit", "acf", "xcorr", "periodogram", "phases")}
    res = [[r["measured"][:, j] - r["predicted"][:, j] for r in runs]
           for j in range(len(columns))]
    dt = _dt(runs)
    shortest = min(len(r["ts"]) for r in runs)
    lag = _max_lag(runs, max_lag)
    _save(_fit_figure(columns, runs, res), out_dir / names["fit"])
    _save(_acf_figure(columns, res, dt, shortest), out_dir / names["acf"])
    _save(_xcorr_figure(columns, runs, res, input_names, dt, lag), out_dir / names["xcorr"])
    _save(_periodogram_figure(columns, res), out_dir / names["periodogram"])
    _save(_phases_figure(columns, runs, res, input_names, boundary_inputs),
          out_dir / names["phases"])
    return names


def error_chart(path: Path, steps: list[dict], columns, noise: dict) -> None:
    """Free-run RMSE per step (log scale), one line per column, each column's noise std
    dashed; `steps` are `report.json` step entries, `noise` column -> std."""
    from matplotlib import rcParams

    fig = new_figure(figsize=(6.5, 3.6))
    ax = fig.subplots()
    x = np.arange(len(steps))
    colors = rcParams["axes.prop_cycle"].by_key()["color"]
    for j, c in enumerate(columns):
        color = colors[j % len(colors)]
        y = np.array([float(s.get("rmse", {}).get(c)) if isinstance(s.get("rmse", {}).get(c),
                      (int, float)) else np.nan for s in steps])
        y[~(y > 0)] = np.nan
        if np.isfinite(y).any():
            ax.plot(x, y, "o-", color=color, label=c)
        sd = noise.get(c)
        if isinstance(sd, (int, float)) and sd > 0:
            ax.axhline(sd, color=color, ls="--", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xticklabels(["start" if not s.get("added") else
                        f"+{s['added'].get('kind', '?')}" for s in steps],
                       rotation=30, ha="right", fontsize=8)
    ax.set_xlabel("step")
    ax.set_ylabel("free-run RMSE")
    ax.set_title("error per step" + (" (dashed: noise std)" if noise else ""), fontsize=9)
    ax.grid(alpha=0.3, which="both")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
