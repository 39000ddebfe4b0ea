"""The Allan deviation plot."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._plots import WIDTH_IN, new_figure, save_figure


def plot_allan(path: str | Path, curves: dict, rate_unit: str = "deg/h",
               title: str = "Overlapping Allan deviation") -> Path:
    """Allan deviation curves on log-log axes, each with its confidence band.

    **Arguments:**

    - `path`: the PNG to write (1200 px wide).
    - `curves`: label -> `AllanDeviation` (e.g. raw, static-compensated,
      observer-compensated), drawn in that order.
    - `rate_unit`: the unit of the rate, for the axis label.
    - `title`: in words.

    **Returns:** `path`.
    """
    fig = new_figure(figsize=(WIDTH_IN, 0.6 * WIDTH_IN))
    ax = fig.subplots()
    for label, a in curves.items():
        line, = ax.loglog(a.taus, a.adev, marker="o", ms=3, label=label)
        ax.fill_between(a.taus, a.lower, a.upper, color=line.get_color(), alpha=0.2, lw=0)
    level = next(iter(curves.values())).ci if curves else None
    ax.set_xlabel("averaging time τ, s")
    ax.set_ylabel(f"Allan deviation, {rate_unit}")
    ax.set_title(title + (f" (bands: {100 * level:.0f} % confidence)" if level else ""))
    if curves:
        ax.legend(loc="best")
    ax.grid(True, which="both", alpha=0.3)
    return save_figure(fig, path)


def plot_trim(path: str | Path, ts, measured, nominal, trimmed, columns, title: str) -> Path:
    """One end-of-line log against the nominal and the trimmed model: per sensor column the
    readings and both predictions (upper panel) and both residuals (lower), against time
    (min). `ts (times,)` s; `measured`, `nominal`, `trimmed (times, columns)` °C."""
    t = np.asarray(ts) / 60.0
    n = len(columns)
    fig = new_figure(figsize=(WIDTH_IN, 3.4 * n + 1))
    axes = np.atleast_1d(fig.subplots(2 * n, 1, sharex=True,
                                      gridspec_kw={"height_ratios": [2, 1] * n}))
    for j, c in enumerate(columns):
        y = np.asarray(measured)[:, j]
        ax = axes[2 * j]
        ax.plot(t, y, ".", ms=2, color="0.4", label=f"{c} measured")
        ax.plot(t, np.asarray(nominal)[:, j], color="tab:orange", lw=1.2, label="nominal model")
        ax.plot(t, np.asarray(trimmed)[:, j], color="tab:blue", lw=1.2, label="trimmed model")
        ax.set_ylabel(f"{c}, °C")
        ax.legend(loc="upper left")
        ax = axes[2 * j + 1]
        ax.plot(t, y - np.asarray(nominal)[:, j], color="tab:orange", lw=0.7)
        ax.plot(t, y - np.asarray(trimmed)[:, j], color="tab:blue", lw=0.7)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("residual, °C")
    fig.suptitle(title)
    axes[-1].set_xlabel("time, min")
    return save_figure(fig, path)
