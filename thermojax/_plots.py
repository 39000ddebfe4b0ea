"""Matplotlib figures written to PNG.

Every figure is a `matplotlib.figure.Figure` on its own Agg canvas, never a pyplot
figure: writing a PNG neither selects nor changes the user's matplotlib backend.
Matplotlib is imported when a figure is made, not with this module.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np


#: Shared styling: every PNG is `WIDTH_IN` × `DPI` = 1200 px wide (at least), with fonts
#: sized for that width. Figures built here or elsewhere go through `save_figure`.
WIDTH_IN = 12.0
DPI = 100
FONT = {"suptitle": 15, "title": 13, "label": 12, "tick": 11, "legend": 10.5}


#: A bias column's unit by its name's ending (docs/formats.md §1: gyro bias in deg/h,
#: accelerometer bias in micro-g; channel names are free).
_BIAS_SUFFIX_UNITS = (("_dph", "deg/h"), ("_ug", "µg"))


def column_unit(column: str, bias: bool = False) -> str:
    """The unit of a measured column, for axis labels and tables: °C for a temperature
    sensor; for a bias channel (`bias=True`) deg/h if its name ends in `_dph`, µg if it
    ends in `_ug`, else "bias unit"."""
    if not bias:
        return "°C"
    for suffix, unit in _BIAS_SUFFIX_UNITS:
        if str(column).endswith(suffix):
            return unit
    return "bias unit"


def column_units(sensor_columns, bias_columns=()) -> dict[str, str]:
    """column -> `column_unit` for every sensor column and bias column."""
    out = {c: column_unit(c) for c in sensor_columns}
    out.update({c: column_unit(c, bias=True) for c in bias_columns})
    return out


def new_figure(**kwargs):
    """A `matplotlib.figure.Figure` drawn by the Agg canvas (no pyplot, no backend
    change); `kwargs` go to `Figure` (`figsize` in inches, width at least `WIDTH_IN`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = kwargs.pop("figsize", (WIDTH_IN, 0.6 * WIDTH_IN))
    fig = Figure(figsize=(max(float(w), WIDTH_IN), float(h)), **kwargs)
    FigureCanvasAgg(fig)
    return fig


def style_figure(fig, grid: bool = True) -> None:
    """The house fonts on every title, axis label, tick label and legend of `fig`."""
    if fig._suptitle is not None:
        fig._suptitle.set_fontsize(FONT["suptitle"])
    for ax in fig.axes:
        ax.title.set_fontsize(FONT["title"])
        ax.xaxis.label.set_fontsize(FONT["label"])
        ax.yaxis.label.set_fontsize(FONT["label"])
        ax.tick_params(labelsize=FONT["tick"])
        legend = ax.get_legend()
        if legend is not None:
            for t in legend.get_texts():
                t.set_fontsize(FONT["legend"])
        if grid:
            ax.grid(alpha=0.3)


#: Matplotlib's text layout is not thread-safe (its mathtext parser keeps state between
#: calls: two threads laying out tick labels such as 10⁻¹ at once raise `ParseException`
#: or `IndexError`), and `investigate` draws figures on a worker thread
#: (`investigation._plots_ahead`) while the loop writes others: every figure is styled,
#: laid out and written under this lock. Building a figure's artists needs no lock.
_LAYOUT_LOCK = threading.Lock()


def save_figure(fig, path: str | Path, tight: bool = True) -> Path:
    """Style `fig`, lay it out and write it to the PNG `path` at `DPI`; returns `path`.
    Safe to call from several threads (`_LAYOUT_LOCK`)."""
    path = Path(path)
    with _LAYOUT_LOCK:
        style_figure(fig)
        if tight:
            fig.tight_layout()
        fig.savefig(path, dpi=DPI, metadata={"Software": "thermojax"})
    return path


def time_constant_groups(time_constants: dict[str, float], ratio: float = 3.0
                         ) -> list[tuple[str, list[str]]]:
    """Nodes grouped by time constant (s): sorted slowest first, a new group wherever
    the next is more than `ratio` times faster. Returns `(label, names)` pairs, the label
    saying the group's range, e.g. "τ ≈ 11–25 s"."""
    order = sorted(time_constants, key=lambda n: -time_constants[n])
    groups: list[list[str]] = []
    for n in order:
        if groups and time_constants[groups[-1][-1]] <= ratio * time_constants[n]:
            groups[-1].append(n)
        else:
            groups.append([n])

    def fmt(x):
        return f"{x:.2g}" if x < 10 else f"{x:.0f}"

    out = []
    for g in groups:
        lo, hi = time_constants[g[-1]], time_constants[g[0]]
        span = fmt(hi) if fmt(lo) == fmt(hi) else f"{fmt(lo)}–{fmt(hi)}"
        out.append((f"τ ≈ {span} s", g))
    return out


def _is_constant(v) -> bool:
    v = np.asarray(v, float)
    return bool(np.ptp(v) <= 1e-9 * max(1.0, float(np.max(np.abs(v)))))


def plot_simulation(path: str | Path, ts, inputs: dict, nodes: dict, sensors: dict,
                    reference: str | None = None, title: str = "", groups=None,
                    dynamic: dict | None = None, dynamic_title: str = "") -> Path:
    """Stacked panels against time (h), one per concern: the chamber temperature (a
    constant heat input is said in the title, not drawn over an axis; a varying one
    gets its own panel), then per group of nodes (`groups`: `(label, names)` pairs,
    e.g. from `time_constant_groups`; default one group) each node minus the
    `reference` node (default the first): the internal gradients, each panel on its
    own scale; and with `dynamic` (label -> (times,) K) a last panel of those curves,
    titled `dynamic_title`.

    `ts` (times,) in s; every value of `inputs`, `nodes` and `sensors` (times,); the
    sensor readings are drawn as dots in the first panel.
    **Returns:** `path`, the PNG written."""
    t_h = np.asarray(ts) / 3600.0
    reference = reference or next(iter(nodes))
    temp_inputs = {k: v for k, v in inputs.items() if not k.startswith("P")}
    power_inputs = {k: v for k, v in inputs.items() if k.startswith("P")}
    constant = {k: float(np.asarray(v)[0]) for k, v in power_inputs.items() if _is_constant(v)}
    varying = {k: v for k, v in power_inputs.items() if k not in constant}
    groups = [(g, [n for n in names if n != reference]) for g, names in
              (groups or [("", list(nodes))])]
    groups = [(g, names) for g, names in groups if names]
    n_panels = 1 + bool(varying) + len(groups) + bool(dynamic)
    fig = new_figure(figsize=(WIDTH_IN, 2.6 * n_panels + 0.8))
    axes = np.atleast_1d(fig.subplots(n_panels, 1, sharex=True))
    ax = axes[0]
    for name, v in temp_inputs.items():
        ax.plot(t_h, v, label=f"{name} (input)", color="k", lw=1.2)
    stride = max(1, len(t_h) // 400)
    for k, (name, v) in enumerate(sensors.items()):
        ax.plot(t_h[::stride], np.asarray(v)[::stride], ls="none", marker=".", ms=3,
                label=f"{name} (sensor)" if k < 4 else None)
    ax.set_ylabel("temperature, °C")
    heat = "; ".join(f"{k} constant {v:.3g} W" for k, v in constant.items())
    ax.set_title("Chamber temperature and sensor readings" + (f" ({heat})" if heat else ""))
    ax.legend(loc="upper left", ncol=2)
    k = 1
    if varying:
        ax = axes[k]
        k += 1
        for name, v in varying.items():
            ax.plot(t_h, v, label=name, lw=0.8)
        ax.set_ylabel("heat input, W")
        ax.set_title("Heat inputs")
        ax.legend(loc="upper left")
    for label, names in groups:
        ax = axes[k]
        k += 1
        for name in names:
            ax.plot(t_h, np.asarray(nodes[name]) - np.asarray(nodes[reference]), label=name)
        ax.set_ylabel(f"node − {reference}, K")
        ax.set_title(f"Internal gradients, nodes with {label}" if label else
                     "Internal gradients")
        ax.legend(loc="upper left", ncol=3)
    if dynamic:
        ax = axes[k]
        for name, v in dynamic.items():
            ax.plot(t_h, v, label=name, lw=1.0)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("K")
        ax.set_title(dynamic_title or "Dynamic part")
        ax.legend(loc="upper left")
    axes[-1].set_xlabel("time, h")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def plot_fit(path: str | Path, ts, measured, predicted, columns, title: str = "",
             units: dict | None = None) -> Path:
    """Measured against model (upper panel of each pair) and the residual (lower), per
    column, against time (h).

    `ts` (times,) in s; `measured`, `predicted` (times, columns) in each column's unit
    (`units`: column -> unit, default °C).
    **Returns:** `path`, the PNG written."""
    units = units or {}
    t_h = np.asarray(ts) / 3600.0
    n = len(columns)
    fig = new_figure(figsize=(WIDTH_IN, 3.6 * n + 1))
    axes = fig.subplots(2 * n, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1] * n})
    axes = np.atleast_1d(axes)
    stride = max(1, len(t_h) // 2000)
    for j, c in enumerate(columns):
        u = units.get(c, "°C")
        y, p = np.asarray(measured)[:, j], np.asarray(predicted)[:, j]
        ax = axes[2 * j]
        ax.plot(t_h[::stride], y[::stride], ".", ms=2, color="0.4", label=f"{c} measured")
        ax.plot(t_h, p, color="tab:blue", lw=1.2, label="model")
        ax.set_ylabel(f"{c}, {u}")
        ax.legend(loc="upper left")
        ax = axes[2 * j + 1]
        ax.plot(t_h, y - p, color="tab:red", lw=0.6)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(f"residual, {u}")
    if title:
        fig.suptitle(title)
    axes[-1].set_xlabel("time, h")
    return save_figure(fig, path)
