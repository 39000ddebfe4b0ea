"""What a missing heat that no law explains looks like (docs/formats.md §3a
`unexplained`): pulses, a drift, a periodic component, or a heat that varies with no
recorded signal."""

from __future__ import annotations

import numpy as np

SHARE = 0.1  # a carrying node is listed when its RMS heat is this share of the largest
MIN_CYCLES = 3  # a period is named only when this many of its cycles fit in the record


def episode_masks(q: list[np.ndarray]) -> list[np.ndarray]:
    """Per run, the samples of an episode of a missing heat `q` (per run, W): where its
    magnitude is above half its peak over all runs. `describe` counts them; the report's
    figure shades them."""
    x = np.concatenate([np.asarray(v, float) for v in q]) if q else np.zeros(0)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    return [np.abs(np.asarray(v, float)) > 0.5 * peak if peak > 0 else
            np.zeros(len(v), bool) for v in q]


def episodes(ts: list[np.ndarray], q: list[np.ndarray]) -> list[list[tuple[float, float]]]:
    """Per run, the episodes of `episode_masks` as `(start, end)` times (s)."""
    out = []
    for t, on in zip(ts, episode_masks(q)):
        t = np.asarray(t, float)
        edges = np.diff(np.concatenate([[0], on.astype(int), [0]]))
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
        out.append([(float(t[a]), float(t[b])) for a, b in zip(starts, ends)])
    return out


def describe(ts: list[np.ndarray], q: list[np.ndarray]) -> str:
    """The shape of a missing heat `q` (per run, W) sampled at `ts` (per run, s)."""
    x = np.concatenate(q)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    if peak == 0.0:
        return "no missing heat"
    on = episode_masks(q)
    episodes = sum(int(np.sum(np.diff(o.astype(int)) == 1)) + int(o[0]) for o in on)
    share = float(np.mean(np.concatenate(on)))
    if episodes >= 2 and share < 0.5:
        dt = float(np.median(np.diff(ts[0]))) if len(ts[0]) > 1 else 1.0
        width = share * x.size * dt / episodes
        return (f"pulses: {episodes} episodes of about {width:.0f} s and "
                f"{np.median(x[np.concatenate(on)]):.3g} W")
    t = np.concatenate(ts)
    if np.std(t) > 0 and abs(np.corrcoef(t, x)[0, 1]) > 0.7:
        return f"a drift of {np.polyfit(t, x, 1)[0] * 3600:.3g} W per hour"
    r = int(np.argmax([len(v) for v in q]))
    if len(q[r]) > 8:
        power = np.abs(np.fft.rfft(q[r] - q[r].mean())) ** 2
        k = int(np.argmax(power[1:]) + 1)
        # k cycles of the strongest Fourier component fit in the record: with fewer than
        # MIN_CYCLES it is the record's own length (one slow swing), not a period
        if k >= MIN_CYCLES and power[k] > 0.3 * power[1:].sum():
            period = len(q[r]) * float(np.median(np.diff(ts[r]))) / k
            return f"a periodic component of period {period:.0f} s"
    return "a heat that varies with no recorded signal"


def unexplained(mh, file: str | None) -> list[dict]:
    """The `unexplained` entries (spec §3a) of a `MissingHeat` that no candidate of the
    vocabulary or the library explained: each carrying node with at least `SHARE` of the
    largest RMS heat, what it looks like and what to record."""
    rms = {}
    for n in mh.carriers:
        j = mh.nodes.index(n)
        rms[n] = float(np.sqrt(np.mean(np.concatenate([h[:, j] for h in mh.heat]) ** 2)))
    top = max(rms.values(), default=0.0)
    out = []
    for n, size in rms.items():
        if top == 0.0 or size < SHARE * top:
            continue
        j = mh.nodes.index(n)
        out.append({
            "where": [n],
            "what": "an unrecorded heat input: " + describe(mh.ts, [h[:, j] for h in mh.heat]),
            "series": file, "rms_W": size,
            "advice": (f"no effect of the vocabulary or the function library, with the "
                       f"recorded columns, explains the heat missing at {n}: record what "
                       "dissipates there (its power, or the signal that switches it) as "
                       "a column and investigate again")})
    return out
