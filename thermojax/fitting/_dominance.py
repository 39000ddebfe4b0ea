"""Samples that alone decide a fit: a least-squares loss follows one glitch it cannot
explain, so a fit whose residual is mostly one sample is not reported converged.

A sample *dominates* when its squared residual is at least `DOMINANT_SHARE` of its
column's sum over every run, in a column of at least `MIN_SAMPLES` measured samples, and
it stands alone: each measured neighbour's residual is under `ALONE` times its own.
Gaussian noise does not dominate (the largest of 200 squared standard normals carries
about 4 % of their sum, under 10 % in 999 draws of 1000, and less as samples are added);
a model error spreads over its time constant, so that a missed lag of one sample period
after a single step, whose first residual carries 86 % of the squared sum, has a
neighbour at 37 % of it and is not taken for a glitch. A logger glitch that the
plausibility check (`measurements/_plausibility.py`) lets through, a 100 K spike in a
25 °C log, dominates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

DOMINANT_SHARE = 0.25
MIN_SAMPLES = 200
ALONE = 0.2


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
    """The dominating samples of a fit, largest share first.

    `columns` (sensors,) names; `experiments` the runs (`outputs` (times, sensors), NaN
    where dropped); `predictions` per run (times, sensors), same units."""
    found = []
    for j, column in enumerate(columns):
        residuals = [e.outputs[:, j] - np.asarray(p)[:, j]
                     for e, p in zip(experiments, predictions)]
        squares = np.concatenate([np.where(np.isfinite(r), r, 0.0) ** 2 for r in residuals])
        if np.isfinite(np.concatenate(residuals)).sum() < MIN_SAMPLES or not squares.sum() > 0:
            continue
        total = squares.sum()
        for r, (e, res) in enumerate(zip(experiments, residuals)):
            size = np.abs(np.where(np.isfinite(res), res, 0.0))
            for k in np.flatnonzero(size ** 2 >= DOMINANT_SHARE * total):
                neighbours = size[[i for i in (k - 1, k + 1) if 0 <= i < size.size]]
                if np.any(neighbours >= ALONE * size[k]):  # a transient, not a glitch
                    continue
                found.append(DominantSample(r, e.name, column, int(k), float(e.ts[k]),
                                            float(e.outputs[k, j]), float(res[k]),
                                            float(res[k] ** 2 / total)))
    return sorted(found, key=lambda d: -d.share)


def dominance_message(found: list[DominantSample]) -> str:
    """Why a fit with dominating samples is not converged, and what to do."""
    return ("the loss follows a sample it cannot explain: "
            + "; ".join(d.describe() for d in found)
            + ". Check that sample (a logger glitch?); `--outliers drop` leaves such samples "
            "out and refits.")


def without_samples(experiments, found: list[DominantSample], columns) -> list:
    """`experiments` with each sample of `found` made a dropped one (NaN); `columns` the
    sensor columns, in the order of each run's `outputs`."""
    out = list(experiments)
    for d in found:
        outputs = out[d.run].outputs.copy()
        outputs[d.row, list(columns).index(d.column)] = np.nan
        out[d.run] = replace(out[d.run], outputs=outputs)
    return out
