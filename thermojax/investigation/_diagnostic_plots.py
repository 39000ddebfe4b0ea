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

from .._plots import WIDTH_IN, new_figure, save_figure
from ..fitting._residual_analysis import (PHASES, cross_correlation, cumulated_periodogram,
                                 ljung_box, pooled_autocorrelation, residuals_by_phase)
from ._diagnostics import (_check_runs, _dt, _label, _phases, _signals, _split_inputs,
                           lag_span, slowest_time_constant)

#: The keys of `diagnostic_plots`, one PNG each.
PLOT_KEYS = ("fit", "acf", "xcorr", "periodogram", "phases")


def _stride(n: int, points: int = 1500) -> int:
    return max(1, n // points)


def _save(fig, path: Path) -> None:
    save_figure(fig, path)


def settling_time(parameters: dict) -> float | None:
    """The model's slowest time constant, s, from a fit's `parameters` (dotted name ->
    {"value", ...}): `_diagnostics.slowest_time_constant`. None when the parameters do
    not say."""
    return slowest_time_constant(parameters)


def _run_title(name) -> str:
    return Path(str(name)).name


def _fit_figure(columns, runs, res, units, title):
    """Rows: (column, residual) pairs; one column of panels per run; time in h."""
    p, nr = len(columns), len(runs)
    fig = new_figure(figsize=(max(WIDTH_IN, min(6.0 * nr, 18.0)), 3.2 * p + 1.0))
    axes = fig.subplots(2 * p, nr, squeeze=False, gridspec_kw={"height_ratios": [2, 1] * p})
    for i, r in enumerate(runs):
        t_h = r["ts"] / 3600.0
        s = _stride(len(t_h))
        for j, c in enumerate(columns):
            ax = axes[2 * j, i]
            ax.plot(t_h[::s], r["measured"][::s, j], ".", ms=2, color="0.4", label="measured")
            ax.plot(t_h[::s], r["predicted"][::s, j], color="tab:blue", lw=1.0, label="model")
            if i == 0:
                ax.set_ylabel(f"{c}, {units.get(c, '°C')}")
            if j == 0:
                ax.set_title(f"run {i}: {_run_title(r['name'])}")
            if i == 0 and j == 0:
                ax.legend(loc="best")
            ax = axes[2 * j + 1, i]
            ax.plot(t_h[::s], res[j][i][::s], color="tab:red", lw=0.6)
            ax.axhline(0, color="k", lw=0.5)
            if i == 0:
                ax.set_ylabel(f"residual, {units.get(c, '°C')}")
        axes[-1, i].set_xlabel("time, h")
    fig.suptitle(f"{title}\nmeasured against model, residual below each")
    return fig


def _acf_figure(columns, res, dt: float, shortest: int, lag: int, title: str):
    """Pooled residual autocorrelation per column over `lag` samples (two slowest time
    constants: a slow residual is seen to decay instead of sitting at 1), with the
    ±1.96/√N band."""
    p = len(columns)
    acf_lags = max(1, min(lag, shortest - 1))
    fig = new_figure(figsize=(WIDTH_IN, 3.0 * p + 1.0))
    axes = fig.subplots(p, 1, squeeze=False)
    x = np.arange(1, acf_lags + 1) * dt
    for j, c in enumerate(columns):
        ax = axes[j, 0]
        rho, n = pooled_autocorrelation(res[j], acf_lags)
        if acf_lags > 60:
            ax.plot(x, rho, color="tab:blue", lw=1.2)
        else:
            ax.vlines(x, 0, rho, color="tab:blue")
        band = 1.96 / math.sqrt(max(n, 1))
        ax.axhspan(-band, band, color="0.85")
        ax.axhline(0, color="k", lw=0.5)
        # scaled to what is there (a fixed ±1 axis flattens a small but significant
        # correlation into the band): at least four bands, at most ±1.05
        top = min(1.05, max(4 * band, 1.15 * float(np.nanmax(np.abs(rho), initial=0.0))))
        ax.set_ylim(-top, top)
        ax.set_ylabel("autocorrelation")
        _, p_lb, lb_lags = ljung_box(res[j])
        # the p alone: the verdict, at the loop's threshold, is the report's
        p_text = "p < 1e-300" if p_lb < 1e-300 else f"p = {p_lb:.2g}"  # as the report
        ax.set_title(f"{c}: Ljung–Box {p_text} over {lb_lags} lags")
    axes[-1, 0].set_xlabel("lag, s")
    fig.suptitle(f"{title}\nresidual autocorrelation, runs pooled "
                 "(grey: ±1.96/√N, where white noise stays)")
    return fig


def _xcorr_figure(columns, runs, res, input_names, dt: float, lag: int, title: str):
    """Per column two panels: its residual against every input, and against every
    input's rate of change, over ±`lag` samples; 95 % band."""
    p = len(columns)
    signals = [_signals(r, input_names) for r in runs]
    fig = new_figure(figsize=(WIDTH_IN, 3.2 * p + 1.0))
    axes = fig.subplots(p, 2, squeeze=False, sharey=True)
    for j, c in enumerate(columns):
        for col, want in enumerate((False, True)):
            ax = axes[j, col]
            band = None
            for s in range(2 * len(input_names)):
                name, deriv, _ = signals[0][s]
                if bool(deriv) != want:
                    continue
                lags, ccf, band = cross_correlation(res[j], [sg[s][2] for sg in signals], lag)
                ax.plot(lags * dt, ccf, lw=0.8 if deriv else 1.2, label=_label(name, deriv))
            if band is not None:
                ax.axhspan(-band, band, color="0.85")
                ax.legend(loc="best")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(f"{c} residual against input " + ("rates" if want else "levels"))
            if col == 0:
                ax.set_ylabel("correlation")
    for ax in axes[-1]:
        ax.set_xlabel("lag, s (positive: input leads)")
    fig.suptitle(f"{title}\nresidual against inputs (grey: 95 % band of no relation)")
    return fig


def _periodogram_figure(columns, res, title: str):
    """Cumulated periodogram per column with the 5 % Kolmogorov-Smirnov band, on a
    logarithmic frequency axis (a slow residual reaches 1 within the lowest frequencies,
    which a linear axis squeezes against its left edge)."""
    p = len(columns)
    fig = new_figure(figsize=(WIDTH_IN, 4.5))
    axes = fig.subplots(1, p, squeeze=False)
    for j, c in enumerate(columns):
        ax = axes[0, j]
        if any(np.isfinite(x).sum() >= 4 for x in res[j]):
            f, cp, bound = cumulated_periodogram(res[j])
            f, cp = np.asarray(f), np.asarray(cp)
            keep = f > 0
            ax.fill_between(f[keep], np.clip(f[keep] - bound, 0, 1),
                            np.clip(f[keep] + bound, 0, 1), color="0.85",
                            label="white noise ± 5 % band")
            ax.plot(f[keep], f[keep], color="k", lw=0.8)
            ax.plot(f[keep], cp[keep], color="tab:blue", lw=1.4, label="residual")
            ax.set_xscale("log")
            if keep.any():
                ax.set_xlim(f[keep][0], 1)
            ax.legend(loc="best")
        ax.set_title(c)
        ax.set_xlabel("frequency / Nyquist (log scale)")
        ax.set_ylim(0, 1.05)
    axes[0, 0].set_ylabel("cumulated periodogram")
    fig.suptitle(f"{title}\ncumulated periodogram of the residual")
    return fig


def _by_unit(columns, units) -> list[tuple[str, list[str]]]:
    """Columns grouped by unit (°C first, then in order of appearance): one panel each,
    so that a bias in deg/h never shares an axis with a temperature."""
    groups: dict[str, list[str]] = {}
    for c in columns:
        groups.setdefault(units.get(c, "°C"), []).append(c)
    return sorted(groups.items(), key=lambda kv: kv[0] != "°C")


def _phases_figure(columns, runs, res, input_names, boundary_inputs, units, title):
    """Grouped bars: mean residual per chamber phase and column, one panel per unit."""
    chamber, powers = _split_inputs(input_names, boundary_inputs)
    ph = [_phases(r, input_names, chamber, powers) for r in runs]
    groups = _by_unit(columns, units)
    by_column = {c: residuals_by_phase(res[columns.index(c)], ph) for c in columns}
    # only the phases the runs have (no empty "power step" slot in a run without power)
    shown = [k for k in PHASES if any(by_column[c][k]["mean"] is not None for c in columns)] \
        or list(PHASES)
    absent = [k.replace("_", " ") for k in PHASES if k not in shown]
    fig = new_figure(figsize=(WIDTH_IN, 4.5))
    axes = np.atleast_1d(fig.subplots(1, len(groups), squeeze=False)[0])
    x = np.arange(len(shown))
    colors = _colors()
    for ax, (unit, cols) in zip(axes, groups):
        width = 0.8 / max(len(cols), 1)
        for j, c in enumerate(cols):
            by = by_column[c]
            means = [by[k]["mean"] if by[k]["mean"] is not None else 0.0 for k in shown]
            ax.bar(x + (j - (len(cols) - 1) / 2) * width, means, width, label=c,
                   color=colors[columns.index(c) % len(colors)])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xticks(x)
        ax.set_xticklabels([k.replace("_", " ") for k in shown],
                           rotation=15 if len(groups) > 1 else 0)
        ax.set_ylabel(f"mean residual, {unit}")
        ax.legend()
        if len(groups) > 1:
            ax.set_title(f"columns in {unit}")
    fig.suptitle(f"{title}\nmean residual per chamber phase"
                 + (f" (none in the runs: {', '.join(absent)})" if absent else ""))
    return fig


def _colors() -> list:
    from matplotlib import rcParams

    return rcParams["axes.prop_cycle"].by_key()["color"]


def diagnostic_plots(out_dir, prefix: str, columns, runs, input_names, boundary_inputs=(),
                     max_lag: int | None = None, time_scale: float | None = None,
                     title: str = "", units: dict | None = None) -> dict[str, str]:
    """Write the diagnostic PNGs into `out_dir`; return their file names (relative to
    `out_dir`, `<prefix>_<key>.png`) by key:

    - `fit`: per column, measured against model over time for each run, residual below;
    - `acf`: pooled residual autocorrelation with the ±1.96/√N band, per column;
    - `xcorr`: cross-correlation of the residual with each input and derivative, bands;
    - `periodogram`: cumulated periodogram with the 5 % Kolmogorov-Smirnov band;
    - `phases`: residual mean per chamber phase, per column.

    Arguments as `diagnose_traces` takes them (`max_lag` in samples). `time_scale`:
    the model's slowest time constant, s (`settling_time`): the auto- and
    cross-correlation lags then span two of it. `title`: the words each figure's title
    starts with (default from `prefix`); `units`: column -> unit (default °C).
    """
    units = units or {}
    title = title or (prefix.replace("step", "Step ") if prefix else "Model")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = _check_runs(columns, runs, input_names)
    pre = f"{prefix}_" if prefix else ""
    names = {k: f"{pre}{k}.png" for k in PLOT_KEYS}
    res = [[r["measured"][:, j] - r["predicted"][:, j] for r in runs]
           for j in range(len(columns))]
    dt = _dt(runs)
    shortest = min(len(r["ts"]) for r in runs)
    lag = lag_span(dt, shortest, time_scale, max_lag)
    _save(_fit_figure(columns, runs, res, units, title), out_dir / names["fit"])
    _save(_acf_figure(columns, res, dt, shortest, lag, title), out_dir / names["acf"])
    _save(_xcorr_figure(columns, runs, res, input_names, dt, lag, title),
          out_dir / names["xcorr"])
    _save(_periodogram_figure(columns, res, title), out_dir / names["periodogram"])
    _save(_phases_figure(columns, runs, res, input_names, boundary_inputs, units, title),
          out_dir / names["phases"])
    return names


def log_ticks(lo: float, hi: float, most: int = 7) -> list[float]:
    """Tick values for a logarithmic axis from `lo` to `hi` (> 0) that never crowd: the
    finest of the mantissa sequences (steps of 0.1, of 0.5, of 1 within a decade, then
    1-2-3-5, 1-2-5, 1-3 and 1) with at most `most` ticks in range, none closer to the
    next than a `2 most`-th of the axis; at least the two ends when fewer than two
    fall inside."""
    lo, hi = float(min(lo, hi)), float(max(lo, hi))
    k0, k1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    span = math.log10(hi / lo) if hi > lo else 1.0
    fine = [tuple(np.round(np.arange(1.0, 10.0, step), 1)) for step in (0.1, 0.5, 1.0)]
    ticks: list[float] = []
    for mantissas in (*fine, (1, 2, 3, 5), (1, 2, 5), (1, 3), (1,)):
        ticks = sorted({float(f"{m * 10.0 ** k:.3g}") for k in range(k0, k1 + 1)
                        for m in mantissas if lo * (1 - 1e-9) <= m * 10.0 ** k <= hi * (1 + 1e-9)})
        gaps = np.diff(np.log10(ticks)) if len(ticks) > 1 else np.array([span])
        if len(ticks) <= most and gaps.min() >= span / (2 * most):
            break
    if len(ticks) > most:  # decades only, thinned
        ticks = ticks[::math.ceil(len(ticks) / most)]
    if len(ticks) < 2:  # the ends, unless one sits on a tick
        ends = [float(f"{lo:.2g}"), float(f"{hi:.2g}")]
        ticks = sorted(set(ticks) | {e for e in ends if all(
            abs(math.log10(e / t)) >= span / (2 * most) for t in ticks)})
    return ticks


def _step_label(i: int, step: dict, width: int = 22) -> str:
    """`i: start` or `i: + kind (where)`, wrapped to `width` characters a line."""
    import textwrap

    added = step.get("added")
    if not added:
        return f"{i}: start"
    where = added.get("where") or []
    text = f"{i}: + {added.get('kind', '?')}" + (f" ({'–'.join(map(str, where))})"
                                                  if where else "")
    return "\n".join(textwrap.wrap(text, width, break_long_words=False,
                                   break_on_hyphens=False))


def error_chart(path: Path, steps: list[dict], columns, noise: dict,
                units: dict | None = None, noise_given: dict | None = None,
                kalman: bool = False) -> None:
    """Free-run RMSE per step (log scale), one line per column, each column's noise std
    as a horizontal line of its colour, one panel per unit (`units`: column -> unit,
    default °C); `steps` are `report.json` step entries (each labelled on the step axis
    with what it added), `noise` column -> std. `noise_given`: column -> True where the
    std was given in the model (a solid line: the floor the error should reach), False
    where it was estimated with the fit (dotted: the fit's own residual scale, which the
    RMSE equals by construction under output error; under the Kalman likelihood,
    `kalman`, the noise the filter assumes, which the free run need not reach); default
    all given. Ticks are `log_ticks`, which never
    overlap."""
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator

    noise_given = noise_given if noise_given is not None else {c: True for c in noise}
    groups = _by_unit(columns, units or {})
    labels = [_step_label(i, s) for i, s in enumerate(steps)]
    lines_per_label = max(lab.count("\n") + 1 for lab in labels) if labels else 1
    fig = new_figure(figsize=(WIDTH_IN, 5.0 + 0.25 * lines_per_label))
    axes = np.atleast_1d(fig.subplots(1, len(groups), squeeze=False)[0])
    x = np.arange(len(steps))
    colors = _colors()
    kinds = set()
    for ax, (unit, cols) in zip(axes, groups):
        values = []
        for c in cols:
            color = colors[columns.index(c) % len(colors)]
            y = np.array([float(s.get("rmse", {}).get(c)) if isinstance(s.get("rmse", {}).get(c),
                          (int, float)) else np.nan for s in steps])
            y[~(y > 0)] = np.nan
            if np.isfinite(y).any():  # markers shrink column by column: equal values
                k = cols.index(c)       # stay visible one inside the other
                ax.plot(x, y, "-", marker="osD^v"[k % 5], ms=max(9 - 2 * k, 4),
                        lw=max(2.4 - 0.6 * k, 1.0), color=color, label=f"{c} RMSE")
                values += list(y[np.isfinite(y)])
            sd = noise.get(c)
            if isinstance(sd, (int, float)) and sd > 0:
                given = bool(noise_given.get(c, True))
                kinds.add(given)
                ax.axhline(sd, color=color, ls="--" if given else ":", lw=1.2,
                           label=f"{c} noise {sd:.2g} {unit} "
                                 + ("(given)" if given else "(estimated)"))
                values.append(sd)
        ax.set_yscale("log")
        if values:
            lo, hi = min(values), max(values)
            pad = (hi / lo) ** 0.08 if hi > lo else 1.3
            ax.set_ylim(lo / pad, hi * pad)
            ticks = log_ticks(lo / pad, hi * pad)
            ax.yaxis.set_major_locator(FixedLocator(ticks))
            ax.set_yticklabels([f"{t:g}" for t in ticks])
            ax.yaxis.set_minor_locator(NullLocator())
            ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(x)
        ax.set_xticklabels(labels, rotation=0 if len(steps) <= 4 else 30,
                           ha="center" if len(steps) <= 4 else "right")
        ax.set_xlim(-0.4, len(steps) - 0.6)
        ax.set_xlabel("step (effect added)")
        ax.set_ylabel(f"free-run RMSE, {unit}")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=9, framealpha=0.85)
        ax.grid(alpha=0.3, which="major")
    how = {True: "dashed: noise std given in the model",
           False: ("dotted: measurement noise std the Kalman fit estimated" if kalman else
                   "dotted: noise std estimated by the fit, equal to its RMSE by construction")}
    fig.suptitle("Error per step of the investigation against the measurement noise"
                 + (f"\n({'; '.join(how[k] for k in sorted(kinds, reverse=True))})"
                    if kinds else ""))
    save_figure(fig, path)
