"""Regularize a real logger file (gaps, jitter, dropped cells) onto a uniform time grid.

Every channel is interpolated linearly between its own finite samples (the
first-order hold the model assumes for continuous signals). Where the two samples
around a grid time are farther apart than `max_gap`, the cell is left empty (a
dropped sample, skipped by fitting), except in the columns named in `fill`, the
model's input columns, which must be finite and are interpolated across the gap.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._errors import InputError
from ._telemetry import Telemetry


MAX_SAMPLES = 50_000_000  # a resampled run longer than this is refused before allocating


@dataclass
class Resampled:
    """A uniformly sampled run and what resampling did to it.

    `ts` (s, `(T,)`) and `channels` (name -> `(T,)`, NaN for an empty cell) are the new
    run; the other fields describe the change for the user.
    """

    ts: np.ndarray
    channels: dict[str, np.ndarray]
    source: str
    dt: float  # new sample period, s
    median_period: float  # of the source, s
    largest_jitter: float  # largest |step − median| / median of the source steps
    gaps: list[tuple[float, float]] = field(default_factory=list)  # (start, end) s, > max_gap
    emptied: dict[str, int] = field(default_factory=dict)  # column -> cells left empty
    filled: dict[str, int] = field(default_factory=dict)  # column -> cells filled in a gap
    max_gap: float = 0.0  # s
    n_source: int = 0  # rows of the source

    def summary(self) -> list[str]:
        """What was done, in plain lines (printed by the command, written as comments)."""
        lines = [f"resampled {self.source}: {self.n_source} rows with median period "
                 f"{self.median_period:g} s (largest jitter {self.largest_jitter:.1%}) to "
                 f"{self.ts.size} rows every {self.dt:g} s from {self.ts[0]:g} s, each channel "
                 "interpolated linearly between its own samples"]
        if self.gaps:
            total = sum(b - a for a, b in self.gaps)
            lines.append(f"{len(self.gaps)} gap(s) longer than {self.max_gap:g} s "
                         f"({total:g} s in all; the first from {self.gaps[0][0]:g} s to "
                         f"{self.gaps[0][1]:g} s)")
        for name, n in self.emptied.items():
            lines.append(f"{name}: {n} cell(s) left empty where its samples are more than "
                         f"{self.max_gap:g} s apart")
        for name, n in self.filled.items():
            lines.append(f"{name}: {n} cell(s) interpolated across gaps (an input column "
                         "must be finite)")
        if self.dt > 1.5 * self.median_period:
            lines.append(f"note: the new period is {self.dt / self.median_period:.1f}x the "
                         "source's; interpolation does not low-pass, so fast content aliases "
                         "(filter before decimating)")
        return lines


def resample(telemetry: Telemetry, dt: float | None = None, *, max_gap: float | None = None,
             fill: tuple[str, ...] = ()) -> Resampled:
    """`telemetry` on the uniform grid `ts[0] + k dt`.

    **Arguments:**

    - `telemetry`: a run as read (steps may be irregular; strictly increasing times).
    - `dt`: the new period, s (> 0); default the median step of the source.
    - `max_gap`: samples farther apart than this (s) are not interpolated between;
      default 3 `dt`.
    - `fill`: columns interpolated across gaps too (the model's inputs).

    **Returns:** a `Resampled` with the new run and a summary of the change.
    """
    ts = np.asarray(telemetry.ts, dtype=float)
    steps = np.diff(ts)
    median = float(np.median(steps))
    dt = median if dt is None else float(dt)
    if not np.isfinite(dt) or dt <= 0:
        raise InputError(f"the new sample period must be positive, got {dt!r}.", field="--dt")
    max_gap = 3.0 * dt if max_gap is None else float(max_gap)
    if not np.isfinite(max_gap) or max_gap < dt:
        raise InputError(f"the largest gap to interpolate over must be at least the sample "
                         f"period ({dt:g} s), got {max_gap!r}.", field="--max-gap")
    unknown = [c for c in fill if c not in telemetry.channels]
    if unknown:
        raise InputError(f"the file has no column {unknown[0]!r} (its columns are "
                         f"{', '.join(telemetry.channels)}).", file=telemetry.path,
                         field=unknown[0])
    span = ts[-1] - ts[0]
    n_grid = int(np.floor(span / dt * (1 + 1e-12))) + 1
    if n_grid > MAX_SAMPLES:
        raise InputError(f"a period of {dt:g} s over the file's {span:g} s gives {n_grid:,} "
                         f"samples, more than the limit of {MAX_SAMPLES:,}; choose a period of "
                         f"at least {span / (MAX_SAMPLES - 1):.3g} s.", file=telemetry.path,
                         field="--dt")
    grid = ts[0] + dt * np.arange(n_grid)
    out = Resampled(ts=grid, channels={}, source=str(telemetry.path), dt=dt,
                    median_period=median, largest_jitter=float(np.max(np.abs(steps - median))
                                                               / median),
                    max_gap=max_gap, n_source=ts.size)
    out.gaps = [(float(ts[k]), float(ts[k + 1])) for k in np.flatnonzero(steps > max_gap)]
    for name, values in telemetry.channels.items():
        new, empty = _interpolate(ts, np.asarray(values, dtype=float), grid, max_gap)
        if name in fill:
            if empty.any():
                keep = np.isfinite(values)
                if keep.sum() < 2:
                    raise InputError("an input column needs at least two finite samples.",
                                     file=telemetry.path, field=name)
                new[empty] = np.interp(grid[empty], ts[keep], values[keep])
                out.filled[name] = int(empty.sum())
        elif empty.any():
            out.emptied[name] = int(empty.sum())
        out.channels[name] = new
    return out


def _interpolate(ts, values, grid, max_gap) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of one channel's finite samples onto `grid`; NaN (and `True`
    in the returned mask) where the bracketing samples are more than `max_gap` apart
    or there is no sample on one side."""
    keep = np.isfinite(values)
    t, v = ts[keep], values[keep]
    new = np.full(grid.shape, np.nan)
    if t.size == 0:
        return new, np.ones(grid.shape, bool)
    right = np.clip(np.searchsorted(t, grid, side="left"), 0, t.size - 1)
    left = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)
    exact = t[right] == grid
    ok = exact | ((t[left] <= grid) & (t[right] >= grid) & (t[right] - t[left] <= max_gap))
    new[ok] = np.interp(grid[ok], t, v)
    return new, ~ok
