"""Telemetry CSV: read, check and write (docs/formats.md §1; pure NumPy).

A telemetry file is a CSV whose first column is `time_s` (seconds, strictly
increasing) and whose other columns are channels named freely. Lines starting with
`#` (after optional whitespace) and blank lines are skipped. A cell may be empty or
`nan` (a dropped sample), read as NaN. Sampling must be uniform up to jitter under
1 % of the median period; a larger irregular step is refused with the line where it
happens.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from .._errors import InputError

TIME_COLUMN = "time_s"

# Largest tolerated deviation of one step from the median step, as a fraction of it.
JITTER_TOLERANCE = 0.01


@dataclasses.dataclass(frozen=True, eq=False)
class Telemetry:
    """One run of telemetry.

    **Arguments:**

    - `ts`: sample times, s, shape `(times,)`, float64, strictly increasing.
    - `channels`: column name -> values, each shape `(times,)`, float64; NaN where a
      cell was empty or `nan`. Insertion order is the file's column order.
    - `path`: the file it was read from, or `None` for data built in memory.
    - `lines`: the 1-based file line number of each data row, shape `(times,)`, int64
      (for error messages). Defaults to `1 .. times` (data row numbers) in memory.

    Arrays are stored read-only. Equality is identity.
    """

    ts: np.ndarray
    channels: dict[str, np.ndarray]
    path: str | None = None
    lines: np.ndarray | None = None

    def __post_init__(self):
        ts = np.array(self.ts, dtype=np.float64)
        if ts.ndim != 1:
            raise InputError(f"`Telemetry(ts=...)` must be one-dimensional, got shape {ts.shape}.",
                             field=TIME_COLUMN)
        n = ts.shape[0]
        channels = {}
        for name, values in dict(self.channels).items():
            a = np.array(values, dtype=np.float64)
            if a.shape != (n,):
                raise InputError(f"`Telemetry(channels=...)` column {name!r} has shape {a.shape}, "
                                 f"expected ({n},) like `ts`.", field=str(name))
            a.setflags(write=False)
            channels[str(name)] = a
        lines = (np.arange(1, n + 1, dtype=np.int64) if self.lines is None
                 else np.array(self.lines, dtype=np.int64))
        if lines.shape != (n,):
            raise InputError(f"`Telemetry(lines=...)` has shape {lines.shape}, expected ({n},).",
                             field="lines")
        ts.setflags(write=False)
        lines.setflags(write=False)
        object.__setattr__(self, "ts", ts)
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "lines", lines)
        object.__setattr__(self, "path", None if self.path is None else str(self.path))

    @property
    def dt(self) -> float:
        """Median sample period, s (NaN with fewer than two samples)."""
        if self.ts.shape[0] < 2:
            return math.nan
        return float(np.median(np.diff(self.ts)))

    @property
    def names(self) -> tuple[str, ...]:
        """Channel names in file order (without `time_s`)."""
        return tuple(self.channels)

    def __len__(self) -> int:
        return int(self.ts.shape[0])

    def column(self, name: str) -> np.ndarray:
        """The values of channel `name` (or `ts` for `"time_s"`), shape `(times,)`."""
        if name == TIME_COLUMN:
            return self.ts
        try:
            return self.channels[name]
        except KeyError:
            raise _missing(self, name) from None

    def __repr__(self) -> str:
        return (f"Telemetry(path={self.path!r}, samples={len(self)}, dt={self.dt:g} s, "
                f"channels={list(self.channels)})")


def _missing(telemetry: Telemetry, name: str) -> InputError:
    available = ", ".join(telemetry.channels) or "(none)"
    return InputError(f"no column {name!r}; the available columns are: {available}. "
                      "Check the spelling in the model, or add the column to the data.",
                      file=telemetry.path, field=name)


def _where(telemetry: Telemetry, index: int) -> tuple[int | None, str]:
    """(line for InputError, words for the message) of data row `index` (0-based)."""
    if telemetry.path is None:
        return None, f"data row {index + 1}"
    return int(telemetry.lines[index]), f"line {int(telemetry.lines[index])}"


# ---------------------------------------------------------------------------
# reading


def _is_skipped(line: str) -> bool:
    s = line.lstrip()
    return not s or s.startswith("#")


def read_telemetry(path: str | os.PathLike, *, uniform: bool = True) -> Telemetry:
    """Read a telemetry CSV file.

    **Arguments:**

    - `path`: the CSV file.
    - `uniform`: refuse steps that differ from the median by more than 1 % (the default;
      `False` reads a raw logger file for `resample`).

    **Returns:** a `Telemetry` with `ts` (s), one float64 channel per other column
    (NaN for empty or `nan` cells) and the line number of each data row.

    **Raises:** `InputError` naming the file, the line and the column for: a missing
    file; no header; a first column other than `time_s`; an empty or duplicate column
    name; a row with the wrong number of cells; a non-numeric cell; an empty or
    non-finite `time_s`; `time_s` not strictly increasing; fewer than two data rows;
    a step that differs from the median step by more than 1 %.
    """
    file = str(path)
    line_numbers, lines = _content_lines(_read_text(path, file))
    if not lines:
        raise InputError(f"the file has no header (it is empty or holds only comments); "
                         f"expected a header line starting with '{TIME_COLUMN},' and data "
                         "rows below it.", file=file)
    header = _header(lines[0], line_numbers[0], file)
    data = lines[1:]
    data_lines = np.asarray(line_numbers[1:], dtype=np.int64)
    if not data:
        raise InputError("the file has a header but no data rows.", file=file,
                         line=line_numbers[0])
    values = _table(data, data_lines, header, file)
    columns = [np.ascontiguousarray(values[:, j]) for j in range(len(header))]
    _check_times(columns[0], data_lines, file, uniform)
    channels = dict(zip(header[1:], columns[1:]))
    return Telemetry(ts=columns[0], channels=channels, path=file, lines=data_lines)


def _read_text(path, file: str) -> str:
    """The file's text (UTF-8, a byte-order mark dropped), refused by its size before it
    is read whole (`_file_size`): neither a huge file nor `/dev/zero` fills memory."""
    from ._file_size import read_bounded

    try:
        return read_bounded(path, file).decode("utf-8-sig")
    except FileNotFoundError:
        raise InputError("no such file; check the path given to --data.", file=file) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a telemetry CSV file.", file=file) from None
    except UnicodeDecodeError as e:
        raise InputError(f"is not UTF-8 text ({e.reason} at byte {e.start}); save the "
                         "telemetry as a UTF-8 CSV file.", file=file) from None


def _content_lines(text: str) -> tuple[list[int], list[str]]:
    """The 1-based numbers and the text of the lines that are neither blank nor comments
    ('#' after optional whitespace)."""
    kept = [(i, line) for i, line in enumerate(text.splitlines(), start=1)
            if line and line[0] != "#" and (not line[0].isspace() or not _is_skipped(line))]
    return [i for i, _ in kept], [line for _, line in kept]


def _header(line: str, line_number: int, file: str) -> list[str]:
    """The column names of the header `line`: `time_s` first, each named, none twice."""
    header = [cell.strip() for cell in _csv_rows([line], [line_number], file)[0]]
    if header[0] != TIME_COLUMN:
        raise InputError(f"the first column is {header[0]!r}, expected '{TIME_COLUMN}' "
                         f"(time in seconds); the header line must start with '{TIME_COLUMN},'.",
                         file=file, line=line_number, field=header[0])
    seen: dict[str, int] = {}
    for k, name in enumerate(header):
        if not name:
            raise InputError(f"column {k + 1} of the header has no name; name every column.",
                             file=file, line=line_number)
        if name in seen:
            raise InputError(f"column name {name!r} appears twice (columns {seen[name] + 1} and "
                             f"{k + 1}); column names must be unique.",
                             file=file, line=line_number, field=name)
        seen[name] = k
    return header


def _table(data: list[str], data_lines: np.ndarray, header: list[str], file: str) -> np.ndarray:
    """The data rows as float64, shape `(rows, columns)`; every row must have one cell
    per header column."""
    n_rows, n_cols = len(data), len(header)
    if any('"' in line for line in data):  # quoted cells: let the csv module split them
        rows = _csv_rows(data, data_lines.tolist(), file)
        counts = np.fromiter(map(len, rows), dtype=np.int64, count=n_rows)
    else:  # plain cells: a comma always separates two cells
        rows = None
        counts = np.fromiter((line.count(",") for line in data), dtype=np.int64,
                             count=n_rows) + 1
    bad = np.flatnonzero(counts != n_cols)
    if bad.size:
        k = int(bad[0])
        raise InputError(f"the row has {int(counts[k])} cells but the header names {n_cols} "
                         f"columns ({', '.join(header)}).", file=file, line=int(data_lines[k]))
    cells = (",".join(data).split(",") if rows is None
             else [cell for row in rows for cell in row])
    return _parse_cells(cells, header, data_lines, file).reshape(n_rows, n_cols)


def _check_times(ts: np.ndarray, data_lines: np.ndarray, file: str, uniform: bool) -> None:
    """`time_s` (s, `(rows,)`) finite, at least two rows, strictly increasing, and (when
    `uniform`) uniform up to `JITTER_TOLERANCE` of the median step."""
    bad = np.flatnonzero(~np.isfinite(ts))
    if bad.size:
        k = int(bad[0])
        raise InputError(f"'{TIME_COLUMN}' is empty or not finite; every row needs a time in "
                         "seconds.", file=file, line=int(data_lines[k]), field=TIME_COLUMN)
    if ts.shape[0] < 2:
        raise InputError("the file holds a single data row; at least two are needed to "
                         "define a sample period.", file=file, line=int(data_lines[0]))
    steps = np.diff(ts)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise InputError(f"'{TIME_COLUMN}' = {float(ts[k])!r} does not increase (the previous row, "
                         f"line {int(data_lines[k - 1])}, has {float(ts[k - 1])!r}); times must be "
                         "strictly increasing.", file=file, line=int(data_lines[k]),
                         field=TIME_COLUMN)
    if not uniform:
        return
    period = float(np.median(steps))
    bad = np.flatnonzero(np.abs(steps - period) > JITTER_TOLERANCE * period)
    if bad.size:
        k = int(bad[0]) + 1
        raise InputError(
            f"irregular sampling: the step from the previous row is {float(steps[k - 1])!r} s "
            f"but the median period is {period!r} s (only jitter under {JITTER_TOLERANCE:.0%} is "
            "tolerated). Put the run on a uniform grid with `thermojax resample`, or split it "
            "into separate files at the gap.", file=file, line=int(data_lines[k]), field=TIME_COLUMN)


def _csv_rows(lines: Sequence[str], line_numbers: Sequence[int], file: str) -> list[list[str]]:
    """Split lines with the csv module, one row per line (a quote may not span lines)."""
    reader = csv.reader(lines, strict=True)
    rows = []
    try:
        for row in reader:
            if reader.line_num != len(rows) + 1:
                raise InputError("a quoted cell is not closed on its line; write one row per "
                                 "line and close every quote.", file=file,
                                 line=line_numbers[len(rows)])
            rows.append(row)
    except csv.Error as e:  # the row that failed starts after the last complete one
        raise InputError(f"malformed CSV ({e}); check the quoting on this line and close "
                         "every quote on the line it opens.",
                         file=file, line=line_numbers[min(len(rows), len(line_numbers) - 1)]) \
            from None
    return rows


def _parse_cells(cells: list[str], header: Sequence[str], lines: np.ndarray,
                 file: str) -> np.ndarray:
    """Parse row-major cells into float64, empty (or blank) cells -> NaN."""
    nan = math.nan
    try:  # fast path: every cell is a number or empty
        return np.array([float(c) if c else nan for c in cells], dtype=np.float64)
    except ValueError:
        pass
    out = np.empty(len(cells), dtype=np.float64)
    n_cols = len(header)
    for k, cell in enumerate(cells):  # slow path: blank cells, or find the offending cell
        text = cell.strip()
        if not text:
            out[k] = nan
            continue
        try:
            out[k] = float(text)
        except ValueError:
            row, col = divmod(k, n_cols)
            raise InputError(f"cell {cell!r} in column {header[col]!r} is not a number (write "
                             "numbers like 12.5 or 1e-3; leave the cell empty or write nan for "
                             "a dropped sample).", file=file, line=int(lines[row]),
                             field=header[col]) from None
    return out


# ---------------------------------------------------------------------------
# checks


def check_inputs(telemetry: Telemetry, columns: Iterable[str]) -> None:
    """Check that input columns exist and hold a finite value on every row.

    **Arguments:**

    - `telemetry`: the run.
    - `columns`: names of input columns (boundary temperatures, powers).

    **Raises:** `InputError` for a missing column (listing the available ones) or an
    empty, `nan` or infinite cell (naming the column and the line).
    """
    for name in columns:
        values = telemetry.column(name)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            line, where = _where(telemetry, int(bad[0]))
            raise InputError(
                f"input column {name!r} is empty or not finite at {where} "
                f"({bad.size} such cells); inputs must be known at every sample. Fill or "
                "interpolate the gap, or split the run there.",
                file=telemetry.path, line=line, field=name)


def check_sensors(telemetry: Telemetry, columns: Iterable[str]) -> None:
    """Check that sensor columns exist and hold at least one reading.

    Empty and `nan` cells are dropped samples and allowed; an infinite reading is not.

    **Arguments:**

    - `telemetry`: the run.
    - `columns`: names of measured columns (sensors, bias channels).

    **Raises:** `InputError` for a missing column (listing the available ones), a
    column with no reading at all, or an infinite cell (naming the line).
    """
    for name in columns:
        values = telemetry.column(name)
        if np.all(np.isnan(values)):
            raise InputError(f"sensor column {name!r} has no readings (every cell is empty or "
                             "nan); drop it from the model or use a run that measured it.",
                             file=telemetry.path, field=name)
        bad = np.flatnonzero(np.isinf(values))
        if bad.size:
            line, where = _where(telemetry, int(bad[0]))
            raise InputError(f"sensor column {name!r} is infinite at {where}; leave the cell "
                             "empty (or nan) for a dropped sample.",
                             file=telemetry.path, line=line, field=name)


# ---------------------------------------------------------------------------
# writing


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not name or name != name.strip() \
            or any(c in name for c in ',"\r\n'):
        raise InputError(f"`write_telemetry(channels=...)`: column name {name!r} must be a "
                         "non-empty string without commas, quotes, line breaks or surrounding "
                         "spaces.", field=str(name))
    if name == TIME_COLUMN:
        raise InputError(f"`write_telemetry(channels=...)`: '{TIME_COLUMN}' is the time column; "
                         "pass the times as `ts`.", field=name)
    return name


def _format(values: np.ndarray) -> list[str]:
    # %.17g round-trips every float64 exactly; NaN is a dropped sample: an empty cell.
    return ["" if v != v else "%.17g" % v for v in values.tolist()]


def write_telemetry(path: str | os.PathLike, ts, channels: Mapping[str, object],
                    comments: Iterable[str] = ()) -> Path:
    """Write a telemetry CSV file that `read_telemetry` reads back bit for bit.

    **Arguments:**

    - `path`: the file to write (overwritten).
    - `ts`: sample times, s, shape `(times,)`.
    - `channels`: column name -> values, each shape `(times,)`; NaN is written as an
      empty cell.
    - `comments`: lines written first, each as `# ...`.

    **Returns:** the path written.
    """
    t = np.asarray(ts, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(f"`write_telemetry(ts=...)` must be one-dimensional, got shape {t.shape}.",
                         field=TIME_COLUMN)
    names = [_check_name(name) for name in channels]
    values = []
    for name in names:
        a = np.asarray(channels[name], dtype=np.float64)
        if a.shape != t.shape:
            raise InputError(f"`write_telemetry(channels=...)` column {name!r} has shape "
                             f"{a.shape}, expected {t.shape} like `ts`.", field=name)
        values.append(a)
    out = []
    for comment in comments:
        for part in str(comment).splitlines() or [""]:
            out.append(f"# {part}".rstrip())
    out.append(",".join([TIME_COLUMN, *names]))
    out.extend(map(",".join, zip(*[_format(v) for v in [t, *values]])))
    path = Path(path)
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.write("\n".join(out) + "\n")
    return path
