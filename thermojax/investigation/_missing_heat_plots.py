"""The missing heat of a step, drawn (docs/formats.md §3a; docs/reports.md).

Per step whose residuals were not white, `investigate` writes `step<K>_missing_heat.csv`:
the heat per node that no term of the model accounts for, with its std. This draws it:
per node that carries heat, the reconstruction over time with its ±2σ band, and below
it the measured temperatures of the sensors nearest that node with the recorded
temperature inputs; the other recorded inputs at the bottom; one column per run. The
episodes the step's `unexplained` entry names are shaded; where the next step added a
learned law at that node, the law's heat (its fitted parameters, evaluated on the
reconstructed node temperatures and the recorded inputs) is drawn over the
reconstruction, so its fit is seen.

NumPy and matplotlib (figures from `_plots.new_figure`); no JAX.
"""

from __future__ import annotations

import csv
from collections import deque
from pathlib import Path

import numpy as np

from .._plots import WIDTH_IN, new_figure, save_figure
from ..discovery._describe import episodes

BAND = 2.0  # the band drawn: ± this many stds


def read_missing_heat(path) -> dict:
    """A `step<K>_missing_heat.csv` (spec §3a) as `{"nodes": [...], "runs": [{"ts",
    "q": {node: (T,)}, "std": {node: (T,)}}]}`, runs in the order of their index."""
    with Path(path).open(newline="") as f:
        rows = list(csv.reader(f))
    head, body = rows[0], np.asarray([[float(v) for v in r] for r in rows[1:] if r], float)
    nodes = [h[2:-2] for h in head[2:] if h.startswith("q_") and h.endswith("_W")]
    col = {h: k for k, h in enumerate(head)}
    runs = []
    if body.size:
        for r in sorted(set(body[:, 1].astype(int))):
            b = body[body[:, 1].astype(int) == r]
            runs.append({"ts": b[:, 0],
                         "q": {n: b[:, col[f"q_{n}_W"]] for n in nodes},
                         "std": {n: b[:, col[f"q_{n}_W_std"]] for n in nodes}})
    return {"nodes": nodes, "runs": runs}


def nearest_sensors(spec) -> dict[str, list[str]]:
    """node -> the sensor columns nearest it in the network (fewest links; an added
    node's effect counts as a link), for every node of `spec` (a `ModelSpec`)."""
    graph: dict[str, set[str]] = {n.name: set() for n in spec.nodes}
    pairs = [tuple(link.between) for link in spec.links]
    pairs += [tuple(e.where[:2]) for e in spec.effects if len(e.where) >= 2]
    for e in spec.effects:
        if e.kind == "extra_node" and e.name:
            pairs.append((e.name, e.where[0]))
    for a, b in pairs:
        if a in graph or b in graph:
            graph.setdefault(a, set()).add(b)
            graph.setdefault(b, set()).add(a)
    read: dict[str, list[str]] = {}
    for s in spec.sensors:
        read.setdefault(s.node, []).append(s.column)
    out = {}
    for start in graph:
        seen, frontier = {start}, deque([(start, 0)])
        found, depth = [], None
        while frontier:
            node, d = frontier.popleft()
            if depth is not None and d > depth:
                break
            if read.get(node):
                found += read[node]
                depth = d
            for nb in graph.get(node, ()):
                if nb not in seen:
                    seen.add(nb)
                    frontier.append((nb, d + 1))
        out[start] = found
    return out


def law_heat(added: dict, node_names, temperatures, input_names, inputs) -> np.ndarray | None:
    """The heat (W) of an added `expression` effect (`report.json`'s `added`: its
    `expression` and fitted `parameters`) at samples of node `temperatures` (T, nodes in
    `node_names`) and `inputs` (T, columns in `input_names`); None when it reads a name
    that is not there."""
    from ..model._expression import ExpressionError, evaluate_numpy, parse, resolve

    expr, params = added.get("expression"), added.get("parameters") or {}
    if not expr:
        return None
    names = list(params)
    try:
        tree = resolve(parse(expr), list(node_names), list(input_names), names)
    except (ExpressionError, ValueError, KeyError):
        return None
    value = evaluate_numpy(tree, temperatures, inputs,
                           np.asarray([float(params[k]) for k in names], float))
    value = np.broadcast_to(np.asarray(value, float), (len(temperatures),))
    return value if np.all(np.isfinite(value)) else None


def _pair(text: str, first, second) -> tuple[str, str] | None:
    """`a-b` of a dotted parameter name split where `a` is in `first` and `b` in
    `second` (names may hold a hyphen themselves)."""
    for k in range(len(text)):
        if text[k] == "-" and text[:k] in first and text[k + 1:] in second:
            return text[:k], text[k + 1:]
    return None


def _value(parameters: dict, key: str) -> float | None:
    p = parameters.get(key)
    v = p.get("value") if isinstance(p, dict) else None
    return float(v) if isinstance(v, (int, float)) and np.isfinite(v) else None


def linear_heat(parameters: dict, node: str, node_names, ts, temperatures, input_names,
                inputs) -> np.ndarray | None:
    """The heat balance of `node` by a step's linear terms (`report.json` step
    `parameters`, dotted names): conduction over its links and boundaries, its heat
    inputs' gains, minus `C dT/dt` (W, at samples `ts` of node `temperatures`
    (T, `node_names`) and `inputs` (T, `input_names`)). None without its capacitance."""
    nodes, cols = list(node_names), list(input_names)
    c = _value(parameters, f"nodes.{node}.capacitance")
    if c is None or node not in nodes:
        return None
    T = np.asarray(temperatures, float)
    u = np.asarray(inputs, float)
    j = nodes.index(node)
    q = -c * np.gradient(T[:, j], np.asarray(ts, float))
    for key in parameters:
        group, _, rest = key.partition(".")
        pair, _, name = rest.rpartition(".")
        v = _value(parameters, key)
        if v is None:
            continue
        if group == "links" and name == "conductance":
            ab = _pair(pair, nodes, nodes)
            if ab and node in ab:
                other = ab[1] if ab[0] == node else ab[0]
                q += v * (T[:, nodes.index(other)] - T[:, j])
        elif group == "boundaries" and name == "conductance":
            ab = _pair(pair, nodes, cols)
            if ab and ab[0] == node:
                q += v * (u[:, cols.index(ab[1])] - T[:, j])
        elif group == "heat_inputs" and name == "gain":
            ab = _pair(pair, nodes, cols)
            if ab and ab[0] == node:
                q += v * u[:, cols.index(ab[1])]
    return q


def added_heat(before: dict, after: dict, node: str, node_names, ts, temperatures,
               input_names, inputs) -> np.ndarray | None:
    """The heat into `node` that step `after` (a `report.json` step that added an
    `expression` law) accounts for beyond step `before`: the law's heat plus the change
    of the linear terms refitted with it (`linear_heat` after minus before), on the same
    temperatures and inputs. This, not the law alone, is what the missing heat of
    `before` should show: a law refitted beside a boundary conductance takes over part
    of its heat (on a generated convection law, the law alone swung ±2 W against a
    missing heat of ±0.3 W). None where a part cannot be evaluated."""
    law = law_heat(after.get("added") or {}, node_names, temperatures, input_names, inputs)
    if law is None:
        return None
    q1 = linear_heat(after.get("parameters") or {}, node, node_names, ts, temperatures,
                     input_names, inputs)
    q0 = linear_heat(before.get("parameters") or {}, node, node_names, ts, temperatures,
                     input_names, inputs)
    if q1 is None or q0 is None:
        return None
    return law + q1 - q0


def _legend_outside(ax) -> None:
    """The legend right of the axes (never over the data), its labels wrapped."""
    import textwrap

    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, ["\n".join(textwrap.wrap(t, 28)) for t in labels], fontsize=9,
                  loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)


def _stride(n: int, points: int = 2000) -> int:
    return max(1, n // points)


def missing_heat_figure(path, series: dict, carriers, traces, columns, input_names,
                        boundary_inputs=(), nearest: dict | None = None,
                        shaded: dict | None = None, laws: dict | None = None,
                        units: dict | None = None, input_units: dict | None = None,
                        title: str = "") -> Path:
    """Write the missing-heat PNG of one step to `path`.

    **Arguments:**

    - `series`: `read_missing_heat`'s dict.
    - `carriers`: the nodes drawn (those that carry heat), one pair of rows each.
    - `traces`: the step's run traces (`_diagnostics`: `ts`, `measured` (T, columns),
      `inputs` (T, inputs)), in the runs' order; may be empty (no temperatures drawn).
    - `columns`, `input_names`, `boundary_inputs`: as the report takes them.
    - `nearest`: node -> the sensor columns drawn under it (default all `columns`).
    - `shaded`: node -> the description whose episodes are shaded (`unexplained`).
    - `laws`: node -> `(label, [heat per run or None])`, drawn over the reconstruction.
    - `units`: column -> unit; `input_units`: input -> unit (boundary inputs °C).
    """
    nearest, shaded, laws = nearest or {}, shaded or {}, laws or {}
    units, input_units = units or {}, dict(input_units or {})
    for b in boundary_inputs:
        input_units.setdefault(b, "°C")
    runs = series["runs"]
    nr = max(len(runs), 1)
    others = [u for u in input_names if u not in boundary_inputs]
    heights = []
    for _ in carriers:
        heights += [2.2, 1.4]
    if others:
        heights.append(1.2)
    fig = new_figure(figsize=(max(WIDTH_IN, min(6.0 * nr + 2.5, 18.0)),
                              1.3 * sum(heights) + 1.4))
    axes = fig.subplots(len(heights), nr, squeeze=False, sharex="col",
                        gridspec_kw={"height_ratios": heights})
    for r, run in enumerate(runs):
        t_h = run["ts"] / 3600.0
        s = _stride(len(t_h))
        tr = traces[r] if r < len(traces) else None
        for k, node in enumerate(carriers):
            ax = axes[2 * k, r]
            q, sd = run["q"][node], run["std"][node]
            ax.fill_between(t_h[::s], (q - BAND * sd)[::s], (q + BAND * sd)[::s],
                            color="tab:blue", alpha=0.25, lw=0,
                            label=f"±{BAND:g}σ band")
            ax.plot(t_h[::s], q[::s], color="tab:blue", lw=1.2, label="reconstructed")
            ax.axhline(0, color="k", lw=0.5)
            if node in shaded:
                eps = episodes([run["ts"] for run in runs],
                               [run["q"][node] for run in runs])[r]
                for j, (a, b) in enumerate(eps):
                    ax.axvspan(a / 3600.0, b / 3600.0, color="tab:orange", alpha=0.18,
                               lw=0, label="episode (unexplained)" if j == 0 else None)
            if node in laws:
                label, heat = laws[node]
                if r < len(heat) and heat[r] is not None:
                    ax.plot(t_h[::s], heat[r][::s], color="tab:red", lw=1.2, ls="--",
                            label=label)
            if r == 0:
                ax.set_ylabel(f"heat into {node}, W")
            if k == 0:
                ax.set_title(f"run {r}")
            if r == nr - 1:
                _legend_outside(ax)
            ax = axes[2 * k + 1, r]
            drawn = False
            if tr is not None:
                tt = np.asarray(tr["ts"]) / 3600.0
                st = _stride(len(tt))
                for c in nearest.get(node, columns):
                    if c in columns:
                        ax.plot(tt[::st], np.asarray(tr["measured"])[::st, columns.index(c)],
                                lw=1.0, label=f"{c} (measured)")
                        drawn = True
                for b in boundary_inputs:
                    if b in input_names:
                        ax.plot(tt[::st], np.asarray(tr["inputs"])[::st, input_names.index(b)],
                                lw=0.8, ls=":", color="0.35", label=f"{b} (input)")
                        drawn = True
            if drawn and r == nr - 1:
                _legend_outside(ax)
            if r == 0:
                ax.set_ylabel("temperature, °C")
        if others:
            ax = axes[-1, r]
            if tr is not None:
                tt = np.asarray(tr["ts"]) / 3600.0
                st = _stride(len(tt))
                for u in others:
                    unit = input_units.get(u)
                    ax.plot(tt[::st], np.asarray(tr["inputs"])[::st, input_names.index(u)],
                            lw=0.9, label=f"{u}, {unit}" if unit else u)
                if r == nr - 1:
                    _legend_outside(ax)
            if r == 0:
                units_seen = {input_units.get(u) for u in others}
                ax.set_ylabel("input, " + units_seen.pop() if len(units_seen) == 1 and
                              None not in units_seen else "recorded input")
        axes[-1, r].set_xlabel("time, h")
    fig.suptitle((f"{title}\n" if title else "") + "missing heat per node (reconstructed, "
                 f"±{BAND:g}σ), nearest sensors' temperatures and the recorded inputs")
    return save_figure(fig, path)


def missing_heat_section(out: Path, i: int, steps: list[dict], traces, columns,
                         input_names, boundary_inputs=(), heat=None,
                         nearest: dict | None = None, units: dict | None = None,
                         input_units: dict | None = None, prefix: str | None = None
                         ) -> list[str]:
    """`### Missing heat` of step `i` (Markdown lines, and its figure
    `step<i>_missing_heat.png` in `out`): where heat is missing and how much, what the
    unexplained part looks like, and the figure. Empty when the step has no missing-heat
    file in `out`. `heat`: the step's `MissingHeat` when at hand (its reconstructed node
    temperatures let an added law be drawn over it). `prefix`: the figure's name is
    `<prefix>_missing_heat.png` (default `step<i>`)."""
    s = steps[i]
    mh = s.get("missing_heat") or {}
    if not mh:
        return []
    md = ["### Missing heat", ""]
    if not mh.get("file") or not (out / mh["file"]).is_file():
        return md + [f"No reconstruction: {mh.get('note') or 'no file was written'}.", ""]
    carriers = list(mh.get("nodes_carrying") or [])
    per = mh.get("per_node") or {}
    if not carriers:
        return md + [f"No node needs a heat flow beyond the model's terms to explain the "
                     f"data ([`{mh['file']}`]({mh['file']}): zero at every node).", ""]
    md.append("Heat that no term of this step's model accounts for, reconstructed per "
              "node (a random-walk heat on the nodes the likelihood chose, Kalman "
              f"smoother; [`{mh['file']}`]({mh['file']})): " + "; ".join(
                  f"{n}: RMS {per[n]['rms_W']:.3g} W, peak {per[n]['peak_W']:+.3g} W, "
                  f"typical std {per[n]['median_std_W']:.2g} W" if n in per else n
                  for n in carriers) + ".")
    shaded = {}
    for u in s.get("unexplained") or []:
        node = (u.get("where") or [None])[0]
        md.append(f"Unexplained at {node}: {u.get('what')}.")
        if node in carriers and "episodes" in str(u.get("what")):
            shaded[node] = u.get("what")
    laws = {}
    nxt = steps[i + 1].get("added") if i + 1 < len(steps) else None
    if nxt and nxt.get("expression") and (nxt.get("where") or [None])[0] in carriers:
        node = nxt["where"][0]
        heats = []
        for r, tr in enumerate(traces or []):
            if heat is None or r >= len(heat.temperatures):
                heats.append(None)
                continue
            heats.append(added_heat(s, steps[i + 1], node, heat.nodes, tr["ts"],
                                    heat.temperatures[r], input_names,
                                    np.asarray(tr["inputs"])))
        if any(h is not None for h in heats):
            laws[node] = (f"step {i + 1}'s law {nxt['expression']} with the terms "
                          "refitted beside it", heats)
            md.append(f"Over the reconstruction at {node}: the heat the model of step "
                      f"{i + 1} accounts for beyond this step's, its law "
                      f"`{nxt['expression']}` plus the change of the linear terms refitted "
                      "with it, on the reconstructed node temperatures.")
    series = read_missing_heat(out / mh["file"])
    name = f"{prefix or f'step{i}'}_missing_heat.png"
    missing_heat_figure(out / name, series, carriers, traces or [], list(columns),
                        list(input_names), boundary_inputs, nearest, shaded, laws, units,
                        input_units, title="The given model" if prefix else f"Step {i}")
    return md + ["", f"![missing heat at step {i}]({name})", ""]
