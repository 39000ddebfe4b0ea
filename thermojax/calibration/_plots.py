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
