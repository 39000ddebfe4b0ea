"""Samples that alone decide a fit: a least-squares loss follows glitches it cannot
explain, so a fit whose residual is mostly one sample, one short burst or a few
scattered glitches is not reported converged.

A *glitch* is a burst of at most `MAX_BURST` consecutive samples of one column whose
residuals are all within a factor `FLAT` of the largest, that largest above `OUTLIER`
robust stds of the column's residuals (1.4826 × their median absolute value), standing
alone: each measured neighbour just outside it has a residual under `ALONE` times the
burst's smallest. A column's glitches *dominate* when together they carry at least
`DOMINANT_SHARE` of its squared residual over every run, in a column of at least
`MIN_SAMPLES` measured samples. Gaussian noise does not dominate (8 robust stds is
beyond any draw of this size, and the largest of 200 squared standard normals carries
about 4 % of their sum); a model error spreads over its time constant and fades, so that
a missed lag of one sample period after a single step, whose first residual carries
86 % of the squared sum, has a neighbour at 37 % of it and is not taken for a glitch, nor
is a slower lag whose residual decays through the burst's edge, nor an offset lasting
longer than `MAX_BURST`. A logger glitch that the plausibility check
(`measurements/_plausibility.py`) lets through (a 100 K spike in a 25 °C log, a few
seconds of a connector reading 5 K off, a handful of such spikes over a run) dominates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

DOMINANT_SHARE = 0.25
MIN_SAMPLES = 200
ALONE = 0.2
MAX_BURST = 10
FLAT = 0.5
OUTLIER = 8.0


@dataclass(frozen=True)
class DominantSample:
    """One sample that carries `share` of its column's squared residual: `run` (index and
    `run_name`), 0-based data `row`, `time_s`, the measured `value` and its `residual`
    (measured minus predicted, the column's unit)."""

    run: int
    run_name: str
    column: str
    row: int
    time_s: float
    value: float
    residual: float
    share: float

    def to_json(self) -> dict:
        return asdict(self)

    def describe(self) -> str:
        return (f"{self.run_name}, {self.column} at data row {self.row + 1} (t = "
                f"{self.time_s:g} s, {self.value:.6g}, residual {self.residual:+.4g}) carries "
                f"{100 * self.share:.0f} % of {self.column}'s squared error")


def dominant_samples(columns, experiments, predictions) -> list[DominantSample]:
    """The samples of the dominating bursts of a fit, largest share first.

    `columns` (sensors,) names; `experiments` the runs (`outputs` (times, sensors), NaN
    where dropped); `predictions` per run (times, sensors), same units."""
    found = []
    for j, column in enumerate(columns):
        residuals = [e.outputs[:, j] - np.asarray(p)[:, j]
                     for e, p in zip(experiments, predictions)]
        measured = np.concatenate([r[np.isfinite(r)] for r in residuals])
        total = float(np.sum(measured ** 2))
        if measured.size < MIN_SAMPLES or not total > 0:
            continue
        large = OUTLIER * 1.4826 * np.median(np.abs(measured))  # robust std × OUTLIER
        column_found = []
        for r, (e, res) in enumerate(zip(experiments, residuals)):
            size = np.abs(np.where(np.isfinite(res), res, 0.0))
            for first, last in _bursts(size, large):
                column_found += [DominantSample(r, e.name, column, int(k), float(e.ts[k]),
                                                float(e.outputs[k, j]), float(res[k]),
                                                float(res[k] ** 2 / total))
                                 for k in range(first, last + 1)]
        if sum(d.share for d in column_found) >= DOMINANT_SHARE:
            found += column_found
    return sorted(found, key=lambda d: -d.share)


def _bursts(size: np.ndarray, large: float) -> list[tuple[int, int]]:
    """`(first, last)` rows of each burst of `size` (|residual| per sample, 0 where not
    measured): grown from each sample above `large`, the largest first, over neighbours
    within `FLAT` of it; kept when it is at most `MAX_BURST` long and stands alone."""
    out, taken = [], np.zeros(size.size, bool)
    for k in sorted(np.flatnonzero(size > large), key=lambda i: -size[i]):
        if taken[k]:
            continue
        first = last = k
        while first > 0 and size[first - 1] >= FLAT * size[k] and last - first < MAX_BURST:
            first -= 1
        while last + 1 < size.size and size[last + 1] >= FLAT * size[k] and \
                last - first < MAX_BURST:
            last += 1
        taken[first:last + 1] = True
        inside = size[first:last + 1]
        outside = size[[i for i in (first - 1, last + 1) if 0 <= i < size.size]]
        if last - first < MAX_BURST and not np.any(outside >= ALONE * inside.min()):
            out.append((first, last))  # else a transient, or a lasting offset
    return out


def dominance_message(found: list[DominantSample]) -> str:
    """Why a fit with dominating samples is not converged, and what to do."""
    one = len(found) == 1
    return (f"the loss follows {'a sample' if one else 'samples'} it cannot explain: "
            + "; ".join(d.describe() for d in found)
            + f". Check {'that sample' if one else 'those samples'} (a logger glitch?); "
            "`--outliers drop` leaves such samples out and refits.")


def without_samples(experiments, found: list[DominantSample], columns) -> list:
    """`experiments` with each sample of `found` made a dropped one (NaN); `columns` the
    sensor columns, in the order of each run's `outputs`."""
    out = list(experiments)
    for d in found:
        outputs = out[d.run].outputs.copy()
        outputs[d.row, list(columns).index(d.column)] = np.nan
        out[d.run] = replace(out[d.run], outputs=outputs)
    return out
