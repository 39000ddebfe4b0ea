"""Is a node's missing heat a function of the recorded signals? If not, what does it
look like (docs/formats.md §3a `unexplained`)?

The missing heat of each carrying node is regressed (weighted by its 1/std², forward
selection of at most `MAX_TERMS` library terms, `_library`) on the smoothed
temperatures and the recorded columns. A node whose best law explains less than
`EXPLAINED_R2` of it is listed as unexplained, with its shape: pulses, a drift or a
periodic component.
"""

from __future__ import annotations

import numpy as np

from ._library import library_columns

MAX_TERMS = 3
EXPLAINED_R2 = 0.5


def best_law(q, w, library: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray, float]:
    """`(terms, coefficients, weighted R²)`: the best law of one or two library terms
    (every pair tried: a power law shows only beside the linear term it bends), then a
    third added greedily; the fewest terms within 0.02 of the best R² are kept."""
    sw = np.sqrt(w)
    tss = float(np.sum(w * (q - np.average(q, weights=w)) ** 2)) or 1.0
    names = list(library)

    def fit(terms):
        X = np.stack([library[t] for t in terms], 1)
        c, *_ = np.linalg.lstsq(X * sw[:, None], q * sw, rcond=None)
        return c, 1 - float(np.sum(w * (q - X @ c) ** 2)) / tss

    if not names:
        return [], np.zeros(0), 0.0
    path = [max(((t,) for t in names), key=lambda ts: fit(ts)[1])]
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    if pairs:
        path.append(max(pairs, key=lambda ts: fit(ts)[1]))
        rest = [t for t in names if t not in path[-1]]
        if rest and len(path[-1]) < MAX_TERMS:
            path.append(max((path[-1] + (t,) for t in rest), key=lambda ts: fit(ts)[1]))
    fits = [fit(ts) for ts in path]
    top = max(r for _, r in fits)
    k = next(i for i, (_, r) in enumerate(fits) if r >= top - 0.02)
    return list(path[k]), fits[k][0], max(fits[k][1], 0.0)


def describe(ts: list[np.ndarray], q: list[np.ndarray]) -> str:
    """What a missing heat looks like: pulses, a drift, a periodic component, or else
    a heat input that varies with no recorded signal."""
    x = np.concatenate(q)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    if peak == 0.0:
        return "no missing heat"
    on = [np.abs(v) > 0.5 * peak for v in q]
    episodes = sum(int(np.sum(np.diff(o.astype(int)) == 1)) + int(o[0]) for o in on)
    share = float(np.mean(np.concatenate(on)))
    if episodes >= 2 and share < 0.5:
        dt = float(np.median(np.diff(ts[0]))) if len(ts[0]) > 1 else 1.0
        width = share * x.size * dt / episodes
        return (f"pulses: {episodes} episodes of about {width:.0f} s and "
                f"{np.median(np.concatenate(q)[np.concatenate(on)]):.3g} W")
    t = np.concatenate(ts)
    if np.std(t) > 0 and abs(np.corrcoef(t, x)[0, 1]) > 0.7:
        return f"a drift of {np.polyfit(t, x, 1)[0] * 3600:.3g} W per hour"
    r = int(np.argmax([len(v) for v in q]))
    if len(q[r]) > 8:
        power = np.abs(np.fft.rfft(q[r] - q[r].mean())) ** 2
        k = int(np.argmax(power[1:]) + 1)
        if power[k] > 0.3 * power[1:].sum():
            period = len(q[r]) * float(np.median(np.diff(ts[r]))) / k
            return f"a periodic component of period {period:.0f} s"
    return "a heat input that varies with no recorded signal"


def explain(mh, spec, runs, file: str | None) -> tuple[list[dict], dict]:
    """Per carrying node of `mh` (`MissingHeat` of a fitted `spec`, lowered): its best
    law in `mh.summary`'s `per_node` entries (`law`, `law_r2`), and the `unexplained`
    entries (spec §3a) of the nodes no law explains. `runs`: the `Telemetry` runs.

    **Returns:** `(unexplained entries, node -> {"law", "law_r2"})`."""
    temps = {n: np.concatenate([T[:, j] for T in mh.temperatures])
             for j, n in enumerate(mh.nodes)}
    sensors = set(spec.sensor_columns)
    names = [c for c in runs[0].names if c not in sensors
             and all(c in t.names for t in runs)]
    cols = {c: np.concatenate([np.asarray(t.column(c), float) for t in runs]) for c in names}
    cols = {c: v for c, v in cols.items() if np.all(np.isfinite(v))}
    temperature_cols = {b.input for b in spec.boundaries}
    out, laws = [], {}
    for node in mh.carriers:
        j = mh.nodes.index(node)
        q = np.concatenate([h[:, j] for h in mh.heat])
        w = np.ones_like(q)  # a smoothed series: its samples are not independent
        neighbours = [b for k in spec.links if node in k.between
                      for b in k.between if b != node and b in temps] + [
            b.input for b in spec.boundaries if b.node == node and b.input in cols]
        inputs = [c for c in cols if c not in temperature_cols]
        library = library_columns(node, neighbours, inputs, temps,
                                  {c: cols[c] for c in cols})
        terms, coef, r2 = best_law(q, w, library)
        laws[node] = {"law": " + ".join(f"{c:.4g} * ({t})" for c, t in zip(coef, terms)),
                      "law_r2": r2}
        if r2 < EXPLAINED_R2:
            out.append({"where": [node], "what": "an unrecorded heat input: " + describe(
                mh.ts, [h[:, j] for h in mh.heat]),
                "series": file, "rms_W": float(np.sqrt(np.mean(q ** 2))),
                "best_law_r2": r2,
                "advice": (f"no function of the recorded signals explains the heat missing "
                           f"at {node}: record what dissipates there (its power, or the "
                           "signal that switches it) as a column and investigate again")})
    return out, laws
