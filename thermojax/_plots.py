"""Matplotlib figures written to PNG.

Every figure is a `matplotlib.figure.Figure` on its own Agg canvas, never a pyplot
figure: writing a PNG neither selects nor changes the user's matplotlib backend.
Matplotlib is imported when a figure is made, not with this module.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def new_figure(**kwargs):
    """A `matplotlib.figure.Figure` drawn by the Agg canvas (no pyplot, no backend
    change); `kwargs` go to `Figure` (`figsize` in inches)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _finish(fig, axes, path: str | Path, dpi: int) -> Path:
    """Grid every axis, tighten the layout and write `fig` to the PNG `path` at `dpi`."""
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    return path


def plot_simulation(path: str | Path, ts, inputs: dict, nodes: dict, sensors: dict,
                    reference: str | None = None, title: str = "") -> Path:
    """Three stacked panels against time (h): inputs (°C, W), node temperatures
    with the sensor readings as dots, and each node minus the `reference` node
    (default the first): the internal gradients.

    `ts` (times,) in s; every value of `inputs`, `nodes` and `sensors` (times,).
    **Returns:** `path`, the PNG written."""
    t_h = np.asarray(ts) / 3600.0
    fig = new_figure(figsize=(10, 9))
    axes = fig.subplots(3, 1, sharex=True)
    temp_inputs = {k: v for k, v in inputs.items() if not k.startswith("P")}
    power_inputs = {k: v for k, v in inputs.items() if k.startswith("P")}
    ax = axes[0]
    for name, v in temp_inputs.items():
        ax.plot(t_h, v, label=name, color="k")
    ax.set_ylabel("°C")
    if power_inputs:
        ax2 = ax.twinx()
        for name, v in power_inputs.items():
            ax2.plot(t_h, v, label=name, color="tab:red", lw=0.8)
        ax2.set_ylabel("W", color="tab:red")
    ax.set_title(title or "inputs")
    ax.legend(loc="upper left")
    ax = axes[1]
    for name, v in nodes.items():
        ax.plot(t_h, v, label=name)
    stride = max(1, len(t_h) // 400)
    for name, v in sensors.items():
        ax.plot(t_h[::stride], np.asarray(v)[::stride], ls="none", marker=".", ms=2,
                color="0.3")
    ax.set_ylabel("node temperature, °C")
    ax.legend(loc="upper left", ncol=3, fontsize=8)
    ax = axes[2]
    reference = reference or next(iter(nodes))
    ref = np.asarray(nodes[reference])
    for name, v in nodes.items():
        if name != reference:
            ax.plot(t_h, np.asarray(v) - ref, label=name)
    ax.set_ylabel(f"node − {reference}, K")
    ax.legend(loc="upper left", ncol=3, fontsize=8)
    ax.set_xlabel("time, h")
    return _finish(fig, axes, path, dpi=110)


def plot_fit(path: str | Path, ts, measured, predicted, columns, title: str = "") -> Path:
    """Measured against model (upper panel of each pair) and the residual (lower), per
    column, against time (h).

    `ts` (times,) in s; `measured`, `predicted` (times, columns) in °C.
    **Returns:** `path`, the PNG written."""
    t_h = np.asarray(ts) / 3600.0
    n = len(columns)
    fig = new_figure(figsize=(10, 3.2 * n + 1))
    axes = fig.subplots(2 * n, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1] * n})
    axes = np.atleast_1d(axes)
    stride = max(1, len(t_h) // 2000)
    for j, c in enumerate(columns):
        y, p = np.asarray(measured)[:, j], np.asarray(predicted)[:, j]
        ax = axes[2 * j]
        ax.plot(t_h[::stride], y[::stride], ".", ms=2, color="0.4", label=f"{c} measured")
        ax.plot(t_h, p, color="tab:blue", lw=1.2, label="model")
        ax.set_ylabel("°C")
        ax.legend(loc="upper left", fontsize=8)
        ax = axes[2 * j + 1]
        ax.plot(t_h, y - p, color="tab:red", lw=0.6)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("residual")
    axes[0].set_title(title)
    axes[-1].set_xlabel("time, h")
    return _finish(fig, axes, path, dpi=100)
