"""Plausibility of telemetry for a model, before any work (docs/formats.md §1; pure NumPy).

Two kinds of finding, each naming the file, the line and the column:

- **Unit mistakes** (always refused): a temperature column logged in kelvin beside
  columns in °C, and `time_s` logged in milliseconds (a sample period so far beyond
  the model's time constants that the run cannot show its dynamics, while a thousandth
  of it would). A sensor column that reads as °F beside boundaries in °C is warned of
  (not refused: a heated node can read as high).
- **Outliers** (refused, or dropped when asked): a cell no thermal quantity of its unit
  can take (|value| ≥ 1e12; a temperature below absolute zero or above 5000 °C), or a
  cell isolated from every other value of its column (a gap above the rest of more than
  `ISOLATION` times the rest's range, and more than a floor in the column's unit, so that
  quantization steps, switched power and short pulses never trigger it: 50 K for a
  temperature, for a power what would heat its node by 100 K in one sample period, and
  for a bias or other input column the largest magnitude of the rest). Dropping makes a
  sensor or bias cell a dropped sample (NaN); an input cell (inputs must be known at every
  sample) is held at its previous good value under `hold = "zoh"` and put on the straight
  line between its nearest good neighbours under `"foh"`.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

from .._errors import InputError
from ..model._spec import ModelSpec
from ._telemetry import Telemetry, _where

OUTLIER_CHOICES = ("stop", "drop")

# A cell is isolated when the gap between it and the rest of its column exceeds this
# many times the range of the rest (and the column's floor).
ISOLATION = 20.0
# At most this many cells at each end of a column are taken as one group of outliers.
MOST_AT_EACH_END = 10
# No temperature (°C), power (W), gyro bias (deg/h) or accelerometer bias (micro-g)
# reaches this magnitude.
ABSURD = 1e12
ABSOLUTE_ZERO = -273.15
HOTTEST = 5000.0  # °C: above the boiling point of most metals
# The isolation floor of a temperature column, K.
TEMPERATURE_FLOOR = 50.0
# The isolation floor of a power column: the power that would heat its node by this many
# kelvin in one sample period at the model's capacitance and gain.
POWER_FLOOR_KELVIN = 100.0
# time_s looks like milliseconds when the median step exceeds this many times the model's
# slowest time constant while a thousandth of it does not exceed ten times that constant.
MS_FACTOR = 100.0
# A temperature column looks like kelvin when its median, less 273.15, is within
# max(KELVIN_TOLERANCE, half the other's range) of a °C column's median.
KELVIN_TOLERANCE = 30.0
# A sensor column looks like °F when it reads this many kelvin above the boundary
# temperatures at nearly every sample and, read as °F, within this many of them.
FAHRENHEIT_MARGIN = 10.0
FAHRENHEIT_SLACK = 5.0


@dataclasses.dataclass(frozen=True)
class Outlier:
    """One implausible cell: its `column`, 0-based data `row`, file `line` (None for
    data built in memory), `value` and `reason` (words)."""

    column: str
    row: int
    line: int | None
    value: float
    reason: str

    def describe(self, telemetry: Telemetry) -> str:
        _, where = _where(telemetry, self.row)
        return f"{where}, column '{self.column}' = {self.value:.6g} ({self.reason})"


def check_plausibility(spec: ModelSpec, telemetry: Telemetry, outliers: str = "stop", *,
                       others: bool = False, unread: tuple[str, ...] = (),
                       can_drop: bool = True) -> tuple[Telemetry, list[Outlier]]:
    """Check a run's values against the model's units and against each other.

    **Arguments:**

    - `spec`: the model: its boundary and sensor columns are temperatures (°C), its heat
      input columns powers (W, times the entry's gain), its `[[biases]]` columns bias
      readings; its capacitances and conductances give the time scale of `time_s` (s).
    - `telemetry`: the run.
    - `outliers`: `"stop"` (default) refuses a run holding an outlier; `"drop"` drops
      them (sensor and bias cells become dropped samples; an input cell is held at its
      previous good value under `hold = "zoh"`, interpolated linearly under `"foh"`).
    - `others`: also look in the columns the model does not read (those `diagnose` and
      `investigate` offer as candidate inputs) for cells of magnitude 1e12 or more (their
      meaning is unknown, so nothing finer); dropped, they are interpolated linearly.
    - `unread`: model columns the command does not read (`compensate`'s reconstructed
      input, which the log may lack): not checked.
    - `can_drop`: False for a command without `--outliers drop` (its refusal then says
      to correct the data).

    **Returns:** `(telemetry, dropped)`: the run (a new one when cells were dropped) and
    the outliers dropped (empty unless `outliers="drop"`).

    **Raises:** `InputError` naming the file, the line and the column of a unit mistake
    (kelvin for °C, milliseconds for seconds), or of the first outlier (listing the
    others) when `outliers="stop"`. Missing columns are named as `Experiment` does.
    """
    if outliers not in OUTLIER_CHOICES:
        raise InputError(f"outliers must be one of {', '.join(OUTLIER_CHOICES)}, got "
                         f"{outliers!r}.", field="outliers")
    kinds = {c: k for c, k in _column_kinds(spec).items() if c not in unread}
    if others:
        kinds.update({c: "other" for c in telemetry.channels if c not in kinds})
    values = {c: telemetry.column(c) for c in kinds}
    _check_milliseconds(spec, telemetry)
    _check_kelvin(telemetry, {c: v for c, v in values.items() if kinds[c] == "temperature"})
    _warn_fahrenheit(telemetry, {c: values[c] for c in spec.boundary_columns if c in values},
                     {c: values[c] for c in spec.sensor_columns if c in values})
    found = []
    for column, kind in kinds.items():
        found.extend(_column_outliers(spec, telemetry, column, kind, values[column]))
    found.sort(key=lambda o: (o.row, o.column))
    if not found:
        return telemetry, []
    if outliers == "stop":
        first = found[0]
        listed = "; ".join(o.describe(telemetry) for o in found[:10])
        more = f"; and {len(found) - 10} more" if len(found) > 10 else ""
        raise InputError(
            f"{len(found)} implausible cell{'s' if len(found) > 1 else ''} for the model "
            f"'{spec.name}': {listed}{more}. "
            + ("Correct the data, or run again with --outliers drop to drop them (a sensor "
               "cell becomes a dropped sample, an input cell is filled from its neighbours "
               "as its hold says)." if can_drop else "Correct the data (or cut the log): "
               "this command needs every sample."),
            file=telemetry.path, line=first.line, field=first.column)
    holds = dict(zip(spec.input_columns, spec.input_holds))
    holds.update({c: "foh" for c, kind in kinds.items() if kind == "other"})
    return _dropped(telemetry, holds, found), found


def _column_kinds(spec: ModelSpec) -> dict[str, str]:
    """Every column the model reads -> "temperature", "power", "bias" or "input"."""
    kinds = {}
    for c in spec.boundary_columns:
        kinds[c] = "temperature"
    for c in spec.heat_columns:
        kinds.setdefault(c, "power")
    for c in spec.input_columns:
        kinds.setdefault(c, "input")
    for c in spec.sensor_columns:
        kinds.setdefault(c, "temperature")
    for b in spec.biases:
        kinds.setdefault(b.column, "bias")
    return kinds


# ---------------------------------------------------------------------------
# unit mistakes


def _check_milliseconds(spec: ModelSpec, telemetry: Telemetry) -> None:
    from ..model._network import local_time_constants

    taus = [t for t in local_time_constants(spec).values() if math.isfinite(t) and t > 0]
    dt = telemetry.dt
    if not taus or not math.isfinite(dt):
        return
    slowest = max(taus)
    if dt > MS_FACTOR * slowest and dt / 1000.0 <= 10.0 * slowest:
        line, _ = _where(telemetry, 1)
        raise InputError(
            f"'time_s' looks like milliseconds: it steps by {dt:.6g} s, {dt / slowest:.3g} "
            f"times the slowest time constant of the model '{spec.name}' ({slowest:.3g} s), "
            "so the run could not show its dynamics. time_s is in seconds "
            "(docs/formats.md §1): divide it by 1000. If it is in seconds, check the "
            "model's capacitances (J/K) and conductances (W/K).",
            file=telemetry.path, line=line, field="time_s")


def _check_kelvin(telemetry: Telemetry, columns: dict[str, np.ndarray]) -> None:
    """A temperature column in kelvin beside one in °C: their medians differ by 273.15."""
    stats = {}
    for c, v in columns.items():
        good = v[np.isfinite(v) & (np.abs(v) < ABSURD)]
        if good.size:
            lo, hi = np.percentile(good, [5, 95])  # robust to a few glitches
            stats[c] = (float(np.median(good)), float(lo), float(hi))
    def kelvin_like(med, lo, hi):
        return med > 150.0 and lo > 173.15 and hi < 473.15

    if stats and all(kelvin_like(*s) for s in stats.values()):
        # every temperature in kelvin: nothing in °C to compare with, but no chamber,
        # building or sensor module runs above 150 °C on every column at once
        c = next(iter(stats))
        row = int(np.flatnonzero(np.isfinite(columns[c]))[0])
        line, _ = _where(telemetry, row)
        raise InputError(
            f"every temperature column ({', '.join(stats)}) lies between 173 and 473 with "
            f"medians from {min(s[0] for s in stats.values()):.5g} to "
            f"{max(s[0] for s in stats.values()):.5g}: the file looks like kelvin. "
            "Temperatures are in °C (docs/formats.md §1): subtract 273.15 from each.",
            file=telemetry.path, line=line, field=c)
    for c, (med, lo, hi) in stats.items():
        if not kelvin_like(med, lo, hi):
            continue
        for r, (med_r, lo_r, hi_r) in stats.items():
            if r == c or med_r >= 150.0:
                continue
            if abs(med - 273.15 - med_r) <= max(KELVIN_TOLERANCE, (hi_r - lo_r) / 2):
                row = int(np.flatnonzero(np.isfinite(columns[c]))[0])
                line, _ = _where(telemetry, row)
                raise InputError(
                    f"column '{c}' looks like kelvin: its median {med:.5g} is {med - med_r:.4g} "
                    f"above that of '{r}' ({med_r:.4g} °C). Temperatures are in °C "
                    f"(docs/formats.md §1): subtract 273.15 from '{c}'.",
                    file=telemetry.path, line=line, field=c)


def _warn_fahrenheit(telemetry: Telemetry, boundaries: dict[str, np.ndarray],
                     sensors: dict[str, np.ndarray]) -> None:
    """Warn of a sensor column that reads above the file's boundary temperatures (their
    mean at each sample) by more than `FAHRENHEIT_MARGIN` at nearly every sample while
    its values read as °F, (v − 32)/1.8, lie on them (within `FAHRENHEIT_SLACK` at the
    median): a log in °F. A warning, not a refusal: a heated node can read so too, if
    its rise happens to be 32 + 0.8 T."""
    if not boundaries:
        return
    b = np.mean(np.stack(list(boundaries.values())), axis=0)
    for c, v in sensors.items():
        ok = np.isfinite(v) & np.isfinite(b) & (np.abs(v) < ABSURD)
        if ok.sum() < 2:
            continue
        raw = v[ok] - b[ok]
        as_f = (v[ok] - 32.0) / 1.8 - b[ok]
        if (np.percentile(raw, 5) > FAHRENHEIT_MARGIN
                and abs(np.median(as_f)) < FAHRENHEIT_SLACK):
            warnings.warn(
                f"{telemetry.path or 'the data'}: column '{c}' reads {np.median(raw):.3g} K "
                f"above the boundary temperatures ({', '.join(boundaries)}) at the median, "
                f"and as °F it would read {np.median(as_f):+.2g} K from them: if it is "
                "in °F, convert it, (v − 32) / 1.8. Temperatures are in °C "
                "(docs/formats.md §1).", stacklevel=3)


# ---------------------------------------------------------------------------
# outliers


def _column_outliers(spec: ModelSpec, telemetry: Telemetry, column: str, kind: str,
                     v: np.ndarray) -> list[Outlier]:
    finite = np.isfinite(v)  # empty, nan and inf cells are the reader's and Experiment's
    reasons: dict[int, str] = {}
    for k in np.flatnonzero(finite & (np.abs(v) >= ABSURD)):
        reasons[int(k)] = f"no {_unit_words(kind)} reaches {ABSURD:.0e}"
    if kind == "temperature":
        for k in np.flatnonzero(finite & (v < ABSOLUTE_ZERO)):
            reasons.setdefault(int(k), "below absolute zero, -273.15 °C")
        for k in np.flatnonzero(finite & (v > HOTTEST)):
            reasons.setdefault(int(k), f"above {HOTTEST:g} °C")
    if kind == "other":  # a column of unknown meaning (a status code, a counter): only the absurd
        return [Outlier(column, k, _where(telemetry, k)[0], float(v[k]), why)
                for k, why in sorted(reasons.items())]
    rest = finite.copy()
    rest[np.fromiter(reasons, dtype=np.int64, count=len(reasons))] = False
    floor = _floor(spec, telemetry, column, kind, v[rest])
    for k, words in _isolated(v, rest, floor).items():
        reasons.setdefault(k, words)
    return [Outlier(column, k, _where(telemetry, k)[0], float(v[k]), why)
            for k, why in sorted(reasons.items())]


def _unit_words(kind: str) -> str:
    return {"temperature": "temperature in °C", "power": "power in W",
            "bias": "bias reading"}.get(kind, "input")


def _floor(spec: ModelSpec, telemetry: Telemetry, column: str, kind: str,
           good: np.ndarray) -> float:
    """The least gap that may count as isolation, in the column's unit."""
    if kind == "temperature":
        return TEMPERATURE_FLOOR
    scale = float(np.max(np.abs(good))) if good.size else 0.0
    if kind == "power":
        capacitance = {n.name: n.capacitance.value for n in spec.nodes}
        dt = telemetry.dt
        floors = [POWER_FLOOR_KELVIN * capacitance[h.node] / (dt * abs(h.gain.value))
                  for h in spec.heat_inputs if h.input == column and h.gain.value != 0
                  and h.node in capacitance]
        if floors and math.isfinite(dt) and dt > 0:
            return max(min(floors), 1e-3 * scale)
    # A unit the model does not know: the gap must exceed every magnitude of the rest.
    return max(scale, 1e-300)


def _isolated(v: np.ndarray, usable: np.ndarray, floor: float) -> dict[int, str]:
    """Cells of `v` (among `usable`) at either end of the column separated from the rest
    by a gap above max(ISOLATION × the rest's range, floor); at most MOST_AT_EACH_END."""
    idx = np.flatnonzero(usable)
    n = idx.size
    m = min(MOST_AT_EACH_END, (n - 3) // 2)
    if m < 1:
        return {}
    order = idx[np.argsort(v[idx], kind="stable")]
    s = v[order]
    found: dict[int, str] = {}
    top = 0
    for j in range(1, m + 1):  # the j largest against the rest (less the m smallest)
        gap, spread = s[n - j] - s[n - j - 1], s[n - j - 1] - s[m]
        if gap > max(ISOLATION * spread, floor):
            top = j
    if top:
        words = _isolation_words(s[m], s[n - top - 1])
        found.update({int(k): words for k in order[n - top:]})
    bottom = 0
    for j in range(1, m + 1):  # the j smallest against the rest (less the m largest)
        gap, spread = s[j] - s[j - 1], s[n - 1 - m] - s[j]
        if gap > max(ISOLATION * spread, floor):
            bottom = j
    if bottom:
        words = _isolation_words(s[bottom], s[n - 1 - m])
        found.update({int(k): words for k in order[:bottom]})
    return found


def _isolation_words(lo: float, hi: float) -> str:
    return f"far outside the rest of the column, which spans {lo:.4g} .. {hi:.4g}"


def _dropped(telemetry: Telemetry, holds: dict[str, str], found: list[Outlier]) -> Telemetry:
    """The run with `found` dropped: a sensor or bias cell becomes a dropped sample (NaN);
    an input cell (inputs are known at every sample) takes its previous good value under
    `hold = "zoh"` (the next where none precedes it), else the straight line between its
    nearest good neighbours."""
    channels = dict(telemetry.channels)
    by_column: dict[str, list[int]] = {}
    for o in found:
        by_column.setdefault(o.column, []).append(o.row)
    for column, rows in by_column.items():
        v = np.array(channels[column], dtype=np.float64)
        if column not in holds:  # a sensor or bias cell: a dropped sample
            v[rows] = np.nan
        else:
            good = np.isfinite(v)
            good[rows] = False
            if not good.any():
                raise InputError("every cell of this input column is implausible; nothing is "
                                 "left to fill the dropped cells from.", file=telemetry.path,
                                 field=column)
            kept = np.flatnonzero(good)
            if holds[column] == "zoh":
                before = np.searchsorted(kept, rows) - 1
                v[rows] = v[kept[np.maximum(before, 0)]]
            else:
                v[rows] = np.interp(telemetry.ts[rows], telemetry.ts[kept], v[kept])
        channels[column] = v
    return Telemetry(ts=telemetry.ts, channels=channels, path=telemetry.path,
                     lines=telemetry.lines)


def describe_dropped(telemetry: Telemetry, dropped: list[Outlier]) -> str:
    """One line for the user: how many cells were dropped, and which (the first ten)."""
    listed = "; ".join(o.describe(telemetry) for o in dropped[:10])
    more = f"; and {len(dropped) - 10} more" if len(dropped) > 10 else ""
    return (f"{telemetry.path or 'data'}: dropped {len(dropped)} implausible "
            f"cell{'s' if len(dropped) > 1 else ''} (--outliers drop): {listed}{more}.")
