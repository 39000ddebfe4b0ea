"""Fault injection into a log and its playback through an exported observer: does the
observer stay bounded while a sensor channel is faulted, and how soon does it recover?

A fault is written `KIND:COLUMN:START[:END[:VALUE]]` (times in s from the log's first
sample):

- `rail`: the reading sits at the channel's high ADC rail (`VALUE` °C, default the
  artifact's rail) from START to END;
- `stuck`: the reading is frozen at its value at START;
- `open`: the front end reports an open circuit (the reading is not used);
- `dropout`: the reading is missing (NaN);
- `wire-break`: the reading is off by `VALUE` K (default 10), plausible but wrong;
- `spike`: one sample at START off by `VALUE` K (default 30); no END.

The faulted log and the clean one are played through the same reference observer; the
verdict compares the two estimates of every sensor reading (`C x + D u + offset`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import InputError

KINDS = ("rail", "stuck", "open", "dropout", "wire-break", "spike")
DEFAULT_OFFSET_K = {"wire-break": 10.0, "spike": 30.0}
#: An estimate within this of the clean run's counts as recovered, K.
RECOVERED_K = 0.05


@dataclasses.dataclass(frozen=True)
class Fault:
    """One injected fault: `kind`, sensor `column`, window `[start_s, end_s]` (s from the
    log's start; a spike has `end_s == start_s`) and `value` (°C for `rail`, K offset
    for `wire-break` and `spike`, else None)."""

    kind: str
    column: str
    start_s: float
    end_s: float
    value: float | None = None

    @property
    def label(self) -> str:
        return f"{self.kind} on {self.column} at {self.start_s:g}–{self.end_s:g} s"


def parse_fault(text: str, columns) -> Fault:
    """A `Fault` from `KIND:COLUMN:START[:END[:VALUE]]`; `columns` are the sensor names."""
    field = "--inject"
    parts = text.split(":")
    if len(parts) < 3 or parts[0] not in KINDS:
        raise InputError(f"{text!r}: expected KIND:COLUMN:START[:END[:VALUE]] with KIND one "
                         f"of {', '.join(KINDS)} (e.g. wire-break:T_case:600:900).",
                         field=field)
    kind, column = parts[0], parts[1]
    if column not in columns:
        raise InputError(f"{text!r}: {column!r} is not a sensor of the observer; its sensors "
                         f"are {', '.join(columns)}.", field=field)
    try:
        numbers = [float(v) for v in parts[2:]]
    except ValueError:
        raise InputError(f"{text!r}: START, END and VALUE must be numbers.",
                         field=field) from None
    if not all(np.isfinite(numbers)):
        raise InputError(f"{text!r}: START, END and VALUE must be finite.", field=field)
    start = numbers[0]
    if kind == "spike":
        if len(numbers) > 2:
            raise InputError(f"{text!r}: a spike is spike:COLUMN:TIME[:VALUE].", field=field)
        value = numbers[1] if len(numbers) == 2 else DEFAULT_OFFSET_K[kind]
        return Fault(kind, column, start, start, value)
    if len(numbers) < 2 or len(numbers) > 3 or (len(numbers) == 3 and kind not in
                                                 ("rail", "wire-break")):
        raise InputError(f"{text!r}: {kind} takes {kind}:COLUMN:START:END"
                         + (":VALUE" if kind in ("rail", "wire-break") else "") + ".",
                         field=field)
    end = numbers[1]
    if not end > start >= 0:
        raise InputError(f"{text!r}: need 0 <= START < END (s from the log's start).",
                         field=field)
    value = numbers[2] if len(numbers) == 3 else DEFAULT_OFFSET_K.get(kind)
    return Fault(kind, column, start, end, value)


def inject(faults, t, y, rails_high, names):
    """The readings `y (T, p)` with `faults` applied, and the open-circuit flags `(T, p)`.

    `t (T,)`: s from the log's start; `rails_high (p,)`: each channel's high rail, °C
    (inf when none); `names`: the sensor names (columns of `y`)."""
    y = np.array(y, float)
    oc = np.zeros(y.shape, bool)
    for f in faults:
        j = list(names).index(f.column)
        when = (t >= f.start_s) & (t <= f.end_s) if f.kind != "spike" else \
            np.arange(t.size) == int(np.argmin(np.abs(t - f.start_s)))
        if not when.any():
            raise InputError(f"the fault '{f.label}' falls outside the log "
                             f"(0–{t[-1]:g} s).", field="--inject")
        if f.kind == "rail":
            level = f.value if f.value is not None else rails_high[j]
            if not np.isfinite(level):
                raise InputError(f"the observer has no ADC rails (export with --rails), so "
                                 f"'{f.label}' needs its VALUE in °C: "
                                 f"rail:{f.column}:{f.start_s:g}:{f.end_s:g}:VALUE.",
                                 field="--inject")
            y[when, j] = level
        elif f.kind == "stuck":
            y[when, j] = y[np.flatnonzero(when)[0], j]
        elif f.kind == "open":
            oc[when, j] = True
        elif f.kind == "dropout":
            y[when, j] = np.nan
        else:   # wire-break, spike: an offset
            y[when, j] += f.value
    return y, oc


def _held(u, input_fault, artifact):
    """The inputs the observer used: a flagged sample replaced by the last good one (the
    value the reference starts with before any)."""
    from ..reference._faults import initial_inputs

    used = np.array(u, float)
    last = initial_inputs(artifact.faults.input_limits_array(artifact.system))
    for k in range(used.shape[0]):
        bad = (int(input_fault[k]) >> np.arange(used.shape[1])) & 1 == 1
        used[k, bad] = last[bad]
        last = used[k]
    return used


@dataclasses.dataclass(frozen=True)
class FaultVerdict:
    """What one fault did: the largest distance of any estimate from the clean run's
    while the fault lasted (`worst_K`), whether every state stayed finite and within the
    plausible range (`bounded`), and the time from the fault's end until every estimate
    is within `RECOVERED_K` of the clean one and stays there (`recovered_after_s`, None
    when it is not by the end of the log)."""

    fault: Fault
    worst_K: float
    bounded: bool
    recovered_after_s: float | None


@dataclasses.dataclass(frozen=True)
class FaultPlayback:
    """A playback with faults: `t (T,)` s, the faulted `readings (T, p)` (°C, NaN when
    missing), `open_circuit (T, p)`, the estimated readings `faulted (T, p)` and `clean
    (T, p)` (°C), the channel masks `in_use`, `healthy`, `wire_break (T,)` of the
    faulted run, its `input_fault` mask and `state_ok` flag `(T,)` and fixed-point
    `saturations` so far (`thermojax.reference.ObserverRun`), and one `FaultVerdict`
    per fault."""

    t: np.ndarray
    readings: np.ndarray
    open_circuit: np.ndarray
    faulted: np.ndarray
    clean: np.ndarray
    in_use: np.ndarray
    healthy: np.ndarray
    wire_break: np.ndarray
    input_fault: np.ndarray
    state_ok: np.ndarray
    saturations: np.ndarray
    verdicts: tuple


def play_faults(artifact, t, u, y, faults, build: str = "float64") -> FaultPlayback:
    """Play `u (T, m)` and readings `y (T, p)` (°C; the artifact's inputs and outputs in
    order) through the artifact's reference observer (`build`: float64, float32 or fixed),
    once clean and once with `faults`; `t (T,)` s from the log's start.

    The observer starts at the steady state of the first input, as firmware would. The
    verdicts come from one playback per fault (the fault alone); the returned series
    from one playback with every fault."""
    s = artifact.system
    offset = artifact.arrays["output_offset"]
    limits = artifact.faults.limits
    rails_high = artifact.faults.rails_array(s.n_outputs)[:, 1]
    bad, oc = inject(faults, t, y, rails_high, artifact.output_names)
    x0 = np.linalg.solve(np.eye(s.n_states) - s.Phi, (s.B0 + s.B1) @ u[0])

    def run(readings, open_circuit):
        if build == "fixed":
            obs = artifact.fixed_observer()
            r = obs.run_physical(x0, u, readings - offset, open_circuit)
        else:
            obs = artifact.float_observer(np.float32 if build == "float32" else np.float64)
            r = obs.run(x0, u, readings - offset, open_circuit | np.isnan(readings))
        x = np.asarray(r.states, float)
        return r, x, x @ s.C.T + _held(u, r.input_fault, artifact) @ s.D.T + offset

    _, _, clean = run(np.asarray(y, float), np.zeros(oc.shape, bool))
    verdicts = []
    for f in faults:   # each fault alone, so that one verdict is not another's
        bad_f, oc_f = inject([f], t, y, rails_high, artifact.output_names)
        _, x, est = run(bad_f, oc_f)
        gap = np.abs(est - clean).max(axis=1)
        gap = np.where(np.isfinite(gap), gap, np.inf)
        inside = np.all(np.isfinite(x) & (x >= limits[0]) & (x <= limits[1]), axis=1)
        during = (t >= f.start_s) & (t <= f.end_s + artifact.dt / 2)
        after = np.flatnonzero(t > f.end_s)
        off = np.flatnonzero(gap[after] > RECOVERED_K)
        if not after.size or (off.size and off[-1] == after.size - 1):
            recovered = None
        else:
            recovered = float(t[after[off[-1] + 1] if off.size else after[0]] - f.end_s)
        verdicts.append(FaultVerdict(f, float(gap[during].max()),
                                     bool(inside[t >= f.start_s].all()), recovered))
    r, x, est = run(bad, oc)
    return FaultPlayback(np.asarray(t, float), bad, oc, est, clean, r.in_use, r.healthy,
                         r.wire_break, r.input_fault, r.state_ok, r.saturations,
                         tuple(verdicts))
