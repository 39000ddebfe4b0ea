"""Chamber profile generators: soaks, ramps, shocks, power steps and PRBS (pure NumPy).

Every generator describes the chamber as an exact continuous function of time and
samples it on the uniform grid `ts = k * dt`, `k = 0 .. n-1`:

- The chamber air temperature is *piecewise linear* between breakpoints. Each sample
  holds the exact value of that function, so between two samples inside one ramp the
  slope is exactly the requested rate (to float64 roundoff), and a breakpoint that
  falls on the grid (the usual case: every built-in profile at `dt = 1 s`) is sampled
  exactly, so a ramp lands on its end temperature.
- A ramp whose duration is not a multiple of `dt` ends between two samples: the last
  sample before the breakpoint still lies on the ramp, and the next sample already
  lies on the following segment (usually the plateau). The phase boundaries keep the
  exact breakpoint times; no rate is altered and no time is stretched.
- A profile always ends on a grid point: if the last breakpoint falls between two
  samples, the final plateau is held to the next grid point (the last phase is
  extended, or a short "dwell" phase is added after a ramp).
- A chamber "step" moves from the old to the new temperature over one sample period,
  `[t_step, t_step + dt]`: the sample at `t_step` still shows the old temperature and
  the one at `t_step + dt` the new one. That is the fastest change a sampled record can
  hold, and it is exact under the first-order-hold (linear) input interpolation used
  for chamber temperatures.
- Power is *piecewise constant* and right-continuous: the sample at the switching
  time already shows the new level, so under a zero-order hold the energy delivered
  is exactly `level * on_time`.

Phases (`Phase(start_s, end_s, kind)`) tile `[0, duration]` without gaps.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import TypeAlias

import numpy as np

from .._errors import InputError

Real: TypeAlias = float | int

PHASE_KINDS = ("dwell", "heating_ramp", "cooling_ramp", "step", "power_step", "power_sweep")

# Chamber envelope of the tactical-IMU calibration rig, °C.
CHAMBER_MIN_C = -55.0
CHAMBER_MAX_C = 105.0

# Fraction of dt within which a breakpoint is taken to be on the grid (roundoff only).
_GRID_SNAP = 1e-9


@dataclasses.dataclass(frozen=True)
class Phase:
    """One labelled stretch of a profile.

    **Arguments:**

    - `start_s`, `end_s`: the exact phase boundaries, s (`end_s >= start_s`).
    - `kind`: one of `"dwell"`, `"heating_ramp"`, `"cooling_ramp"`, `"step"`,
      `"power_step"`, `"power_sweep"`.
    """

    start_s: float
    end_s: float
    kind: str

    def __post_init__(self):
        if self.kind not in PHASE_KINDS:
            raise InputError(f"`Phase(kind={self.kind!r})` is not a phase kind; "
                             f"expected one of {', '.join(PHASE_KINDS)}.", field="kind")
        if not (math.isfinite(self.start_s) and math.isfinite(self.end_s)) \
                or self.end_s < self.start_s:
            raise InputError(f"`Phase(start_s={self.start_s}, end_s={self.end_s})` must have "
                             "finite boundaries with end_s >= start_s.", field="end_s")
        object.__setattr__(self, "start_s", float(self.start_s))
        object.__setattr__(self, "end_s", float(self.end_s))

    @property
    def duration(self) -> float:
        """Length of the phase, s."""
        return self.end_s - self.start_s


@dataclasses.dataclass(frozen=True, eq=False)
class Profile:
    """A sampled chamber profile.

    **Arguments:**

    - `ts`: sample times, s, shape `(times,)`; starts at 0 with a uniform step `dt`.
    - `temperature`: chamber air temperature at each sample, °C, shape `(times,)`.
    - `power`: dissipated power at each sample, W, shape `(times,)`; zeros unless a
      power profile set it. Piecewise constant (use a zero-order hold).
    - `phases`: the labelled stretches, tiling `[0, duration]`.

    Arrays are stored as read-only float64. Equality is identity (arrays inside).
    """

    ts: np.ndarray
    temperature: np.ndarray
    power: np.ndarray
    phases: tuple[Phase, ...] = ()

    def __post_init__(self):
        arrays = {}
        for name in ("ts", "temperature", "power"):
            a = np.array(getattr(self, name), dtype=np.float64)
            if a.ndim != 1:
                raise InputError(f"`Profile({name}=...)` must be one-dimensional, got shape "
                                 f"{a.shape}.", field=name)
            if not np.all(np.isfinite(a)):
                raise InputError(f"`Profile({name}=...)` holds a non-finite value.", field=name)
            a.setflags(write=False)
            arrays[name] = a
        n = arrays["ts"].shape[0]
        for name in ("temperature", "power"):
            if arrays[name].shape[0] != n:
                raise InputError(f"`Profile({name}=...)` has {arrays[name].shape[0]} samples "
                                 f"but `ts` has {n}.", field=name)
        ts = arrays["ts"]
        if n < 2:
            raise InputError(f"`Profile(ts=...)` needs at least two samples, got {n}.",
                             field="ts")
        if ts[0] != 0.0:
            raise InputError(f"`Profile(ts=...)` must start at 0 s, got {ts[0]!r}.", field="ts")
        dt = ts[1] - ts[0]
        steps = np.diff(ts)
        if not (dt > 0) or not np.allclose(steps, dt, rtol=1e-9, atol=0.0):
            raise InputError("`Profile(ts=...)` must be uniformly increasing "
                             "(ts = k * dt).", field="ts")
        for name, a in arrays.items():
            object.__setattr__(self, name, a)
        phases = tuple(self.phases)
        if not all(isinstance(p, Phase) for p in phases):
            raise InputError("`Profile(phases=...)` must hold `Phase` objects.", field="phases")
        object.__setattr__(self, "phases", phases)

    @property
    def dt(self) -> float:
        """Sample period, s."""
        return float(self.ts[1] - self.ts[0])

    @property
    def duration(self) -> float:
        """Time of the last sample, s (`(len(self) - 1) * dt`)."""
        return float(self.ts[-1])

    def __len__(self) -> int:
        return int(self.ts.shape[0])

    def __repr__(self) -> str:
        kinds = ", ".join(p.kind for p in self.phases[:6])
        more = ", ..." if len(self.phases) > 6 else ""
        return (f"Profile(samples={len(self)}, dt={self.dt:g} s, duration={self.duration:g} s, "
                f"phases=[{kinds}{more}])")


# ---------------------------------------------------------------------------
# validation helpers


def _finite(call: str, name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"`{call}({name}={value!r})` must be a number.", field=name) from None
    if not math.isfinite(v):
        raise InputError(f"`{call}({name}={value!r})` must be finite.", field=name)
    return v


def _positive(call: str, name: str, value) -> float:
    v = _finite(call, name, value)
    if v <= 0:
        raise InputError(f"`{call}({name}={value!r})` must be > 0.", field=name)
    return v


def _nonnegative(call: str, name: str, value) -> float:
    v = _finite(call, name, value)
    if v < 0:
        raise InputError(f"`{call}({name}={value!r})` must be >= 0.", field=name)
    return v


def _in_chamber(call: str, name: str, value) -> float:
    v = _finite(call, name, value)
    if not (CHAMBER_MIN_C <= v <= CHAMBER_MAX_C):
        raise InputError(f"`{call}({name}={value!r})` is outside the chamber range "
                         f"{CHAMBER_MIN_C:g}..{CHAMBER_MAX_C:g} °C.", field=name)
    return v


# ---------------------------------------------------------------------------
# exact piecewise construction


class _Builder:
    """Accumulates an exact piecewise description, then samples it on `k * dt`.

    Temperature knots `(t, T)` are joined linearly; power knots `(t, P)` hold their
    value until the next knot (right-continuous).
    """

    def __init__(self, call: str, start_c: float, dt: float, power_w: float = 0.0):
        self.call = call
        self.dt = dt
        self.t = 0.0
        self.temp_t = [0.0]
        self.temp_v = [float(start_c)]
        self.power_t = [0.0]
        self.power_v = [float(power_w)]
        self.phases: list[Phase] = []

    @property
    def temperature(self) -> float:
        return self.temp_v[-1]

    def _advance(self, duration: float) -> float:
        t = self.t + duration
        k = round(t / self.dt)
        if abs(t - k * self.dt) <= _GRID_SNAP * self.dt:
            t = k * self.dt  # on the grid up to roundoff: sample it exactly
        return t

    def _phase(self, t_end: float, kind: str):
        if self.phases and self.phases[-1].kind == kind and kind in ("dwell", "power_sweep"):
            # merge consecutive dwells into one plateau, a sweep's samples into one phase
            self.phases[-1] = Phase(self.phases[-1].start_s, t_end, kind)
        else:
            self.phases.append(Phase(self.t, t_end, kind))
        self.t = t_end

    def hold(self, duration: float, kind: str = "dwell"):
        """Keep the temperature for `duration` s."""
        if duration <= 0:
            return
        t_end = self._advance(duration)
        self.temp_t.append(t_end)
        self.temp_v.append(self.temperature)
        self._phase(t_end, kind)

    def ramp_to(self, end_c: float, rate_c_per_min: float):
        """Move linearly to `end_c` at `rate_c_per_min` (a magnitude), °C/min."""
        delta = end_c - self.temperature
        if delta == 0:
            return
        t_end = self._advance(abs(delta) / rate_c_per_min * 60.0)
        self.temp_t.append(t_end)
        self.temp_v.append(float(end_c))
        self._phase(t_end, "heating_ramp" if delta > 0 else "cooling_ramp")

    def step_to(self, end_c: float):
        """Move to `end_c` over one sample period (a "step" phase)."""
        t_end = self._advance(self.dt)
        self.temp_t.append(t_end)
        self.temp_v.append(float(end_c))
        self._phase(t_end, "step")

    def power(self, level_w: float):
        """Switch the power to `level_w` W from the current time on."""
        if self.power_t[-1] == self.t:
            self.power_v[-1] = float(level_w)
        else:
            self.power_t.append(self.t)
            self.power_v.append(float(level_w))

    def build(self) -> Profile:
        dt = self.dt
        if self.t <= 0:
            raise InputError(f"`{self.call}(...)` describes a profile of zero duration.")
        n_steps = math.ceil(self.t / dt - _GRID_SNAP)
        t_last = n_steps * dt
        if t_last > self.t:
            # last breakpoint between two samples: hold the final plateau to the grid
            self.hold(t_last - self.t)
        ts = np.arange(n_steps + 1, dtype=np.float64) * dt
        temperature = _sample_linear(np.asarray(self.temp_t), np.asarray(self.temp_v), ts)
        power = _sample_constant(np.asarray(self.power_t), np.asarray(self.power_v), ts)
        return Profile(ts=ts, temperature=temperature, power=power, phases=tuple(self.phases))


def _sample_linear(knot_t: np.ndarray, knot_v: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Evaluate the piecewise-linear function through the knots at `ts`.

    Knots are non-decreasing in time; at a repeated knot time the later value applies
    (right-continuous). Beyond the last knot the last value is held.
    """
    i = np.searchsorted(knot_t, ts, side="right") - 1
    i = np.clip(i, 0, len(knot_t) - 1)
    j = np.minimum(i + 1, len(knot_t) - 1)
    t0, t1, v0, v1 = knot_t[i], knot_t[j], knot_v[i], knot_v[j]
    span = t1 - t0
    inside = span > 0
    slope = np.where(inside, (v1 - v0) / np.where(inside, span, 1.0), 0.0)
    return np.where(inside, v0 + slope * (ts - t0), v0)


def _sample_constant(knot_t: np.ndarray, knot_v: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Evaluate the right-continuous piecewise-constant function at `ts`."""
    i = np.searchsorted(knot_t, ts, side="right") - 1
    return knot_v[np.clip(i, 0, len(knot_t) - 1)]


def _dt(call: str, dt) -> float:
    return _positive(call, "dt", dt)


# ---------------------------------------------------------------------------
# generators


def soak(temperature_c: Real, duration_s: Real, *, dt: Real = 1.0) -> Profile:
    """A constant chamber temperature (one "dwell" phase).

    **Arguments:**

    - `temperature_c`: chamber temperature, °C.
    - `duration_s`: length, s (> 0).
    - `dt`: sample period, s.

    **Returns:** a `Profile` with `ceil(duration_s / dt) + 1` samples.
    """
    call = "soak"
    dt = _dt(call, dt)
    b = _Builder(call, _finite(call, "temperature_c", temperature_c), dt)
    b.hold(_positive(call, "duration_s", duration_s))
    return b.build()


dwell = soak
"""Alias of `soak`."""


def ramp(start_c: Real, end_c: Real, rate_c_per_min: Real, *, dt: Real = 1.0) -> Profile:
    """A linear chamber ramp from `start_c` to `end_c`.

    `T(t) = start_c ± rate · t / 60` until `end_c` is reached after
    `|end_c − start_c| / rate · 60` s. The phase is "heating_ramp" or "cooling_ramp"
    by the sign of `end_c − start_c`. If that duration is not a multiple of `dt`, the
    profile is held at `end_c` to the next sample (a short trailing "dwell" phase).

    **Arguments:**

    - `start_c`, `end_c`: chamber temperatures, °C (must differ).
    - `rate_c_per_min`: ramp rate magnitude, °C/min (> 0).
    - `dt`: sample period, s.
    """
    call = "ramp"
    dt = _dt(call, dt)
    start = _finite(call, "start_c", start_c)
    end = _finite(call, "end_c", end_c)
    rate = _positive(call, "rate_c_per_min", rate_c_per_min)
    if start == end:
        raise InputError(f"`ramp(start_c={start_c!r}, end_c={end_c!r})` has no span; "
                         "use `soak` for a constant temperature.", field="end_c")
    b = _Builder(call, start, dt)
    b.ramp_to(end, rate)
    return b.build()


def step_shock(start_c: Real, end_c: Real, before_s: Real, after_s: Real, *,
               dt: Real = 1.0) -> Profile:
    """A chamber thermal shock: dwell at `start_c`, step to `end_c`, dwell there.

    Phases: "dwell" `[0, before_s]`, "step" `[before_s, before_s + dt]` (the chamber
    moves over one sample period), "dwell" `[before_s + dt, before_s + after_s]`.

    **Arguments:**

    - `start_c`, `end_c`: chamber temperatures before and after, °C.
    - `before_s`: time before the step, s (>= 0).
    - `after_s`: time from the step to the end, s (>= dt).
    - `dt`: sample period, s.
    """
    call = "step_shock"
    dt = _dt(call, dt)
    start = _finite(call, "start_c", start_c)
    end = _finite(call, "end_c", end_c)
    before = _nonnegative(call, "before_s", before_s)
    after = _finite(call, "after_s", after_s)
    if after < dt:
        raise InputError(f"`step_shock(after_s={after_s!r})` must be at least one sample "
                         f"period (dt={dt:g} s).", field="after_s")
    b = _Builder(call, start, dt)
    b.hold(before)
    b.step_to(end)
    b.hold(after - dt)
    return b.build()


def viscoelastic_dwell(start_c: Real = 25.0, end_c: Real = 85.0, before_s: Real = 600.0,
                       soak_s: Real = 3 * 3600.0, *, dt: Real = 1.0) -> Profile:
    """The viscoelastic dwell: a rapid step to +85 °C, then a 3 h soak.

    Same shape as `step_shock(start_c, end_c, before_s, soak_s)`.

    **Arguments:**

    - `start_c`, `end_c`: chamber temperatures, °C.
    - `before_s`: dwell before the step, s.
    - `soak_s`: soak after the step, s.
    - `dt`: sample period, s.
    """
    return step_shock(start_c, end_c, before_s, soak_s, dt=dt)


def power_step(level_w: Real, before_s: Real, on_s: Real, after_s: Real, *,
               temperature_c: Real = 25.0, dt: Real = 1.0) -> Profile:
    """A heater power step at constant chamber temperature.

    Power is `level_w` on `[before_s, before_s + on_s)` and 0 elsewhere (sampled
    right-continuously: use a zero-order hold). Phases: "dwell", "power_step", "dwell".

    **Arguments:**

    - `level_w`: power while on, W.
    - `before_s`, `after_s`: quiet time before and after, s (>= 0).
    - `on_s`: time on, s (> 0).
    - `temperature_c`: chamber temperature, °C.
    - `dt`: sample period, s.
    """
    call = "power_step"
    dt = _dt(call, dt)
    level = _finite(call, "level_w", level_w)
    before = _nonnegative(call, "before_s", before_s)
    on = _positive(call, "on_s", on_s)
    after = _nonnegative(call, "after_s", after_s)
    b = _Builder(call, _finite(call, "temperature_c", temperature_c), dt)
    b.hold(before)
    b.power(level)
    b.hold(on, kind="power_step")
    b.power(0.0)
    b.hold(after)
    return b.build()


def power_sweep(level_w: Real, periods_s=(300.0, 30.0), cycles=(2, 10), *,
                temperature_c: Real = 25.0, dt: Real = 1.0) -> Profile:
    """A heater power swept at a few frequencies in turn, at constant chamber temperature:
    the two-point frequency end-of-line test.

    For each period `P` (s) in turn, `cycles` whole cycles of
    `level_w (1 − cos(2π t / P)) / 2` (0 at each start and end, `level_w` at the peak),
    held over each sample (use a zero-order hold). One "power_sweep" phase.

    **Arguments:**

    - `level_w`: peak power, W.
    - `periods_s`: the periods, s (each at least `4 dt`).
    - `cycles`: whole cycles per period (each ≥ 1).
    - `temperature_c`: chamber temperature, °C.
    - `dt`: sample period, s.
    """
    call = "power_sweep"
    dt = _dt(call, dt)
    level = _finite(call, "level_w", level_w)
    periods = [_positive(call, "periods_s", v) for v in periods_s]
    if len(periods) != len(cycles) or not periods:
        raise InputError(f"`power_sweep` needs one cycle count per period, got "
                         f"{len(periods)} periods and {len(cycles)} counts.", field="cycles")
    b = _Builder(call, _finite(call, "temperature_c", temperature_c), dt)
    for P, n in zip(periods, cycles):
        if P < 4 * dt:
            raise InputError(f"`power_sweep`: a period of {P:g} s is under four samples of "
                             f"{dt:g} s.", field="periods_s")
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InputError(f"`power_sweep`: cycles must be whole numbers ≥ 1, got {n!r}.",
                             field="cycles")
        for k in range(int(round(n * P / dt))):
            b.power(level * 0.5 * (1.0 - math.cos(2.0 * math.pi * k * dt / P)))
            b.hold(dt, kind="power_sweep")
    b.power(0.0)
    return b.build()


# Maximal-length Fibonacci LFSR taps (primitive trinomials/pentanomials), register
# length m -> tap positions (1-based). Each gives the period 2**m - 1.
_LFSR_TAPS = {
    3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5),
    10: (10, 7), 11: (11, 9), 12: (12, 6, 4, 1), 13: (13, 4, 3, 1), 14: (14, 5, 3, 1),
    15: (15, 14), 16: (16, 15, 13, 4), 17: (17, 14), 18: (18, 11), 19: (19, 6, 2, 1),
    20: (20, 17), 21: (21, 19), 22: (22, 21), 23: (23, 18), 24: (24, 23, 22, 17),
}


def _lfsr_bits(n_bits: int, seed: int, order: int | None = None) -> np.ndarray:
    """`n_bits` bits (0/1, int8) of a maximal-length LFSR sequence.

    The register length is the smallest `m >= 3` with `2**m - 1 >= n_bits` (unless
    `order` is given); `seed` picks the nonzero initial state, so different seeds give
    cyclic shifts of the same m-sequence.
    """
    m = order if order is not None else max(3, int(n_bits).bit_length())
    taps = _LFSR_TAPS[m]
    period = (1 << m) - 1
    state = 1 + seed % period
    mask = (1 << m) - 1
    out = np.empty(n_bits, dtype=np.int8)
    for k in range(n_bits):
        fb = 0
        for tap in taps:
            fb ^= (state >> (tap - 1)) & 1
        state = ((state << 1) | fb) & mask
        out[k] = fb
    return out


def prbs_power(level_w: Real, bit_s: Real, n_bits: int, seed: int = 0, *,
               temperature_c: Real = 25.0, dt: Real = 1.0) -> Profile:
    """A pseudo-random binary sequence of heater power at constant chamber temperature.

    Bit `k` sets the power to `level_w` (bit 1) or 0 (bit 0) on
    `[k · bit_s, (k + 1) · bit_s)`; the last sample (at `n_bits · bit_s`) is 0. The bits
    come from a maximal-length linear-feedback shift register (an m-sequence: over a
    full period `2**m − 1` it has `2**(m−1)` ones and a flat spectrum), so the sequence
    is deterministic per `seed`. Phases: "power_step" while on, "dwell" while off.

    **Arguments:**

    - `level_w`: power of a 1 bit, W.
    - `bit_s`: bit length, s (> 0; a multiple of `dt` keeps switching on samples).
    - `n_bits`: number of bits (1 .. 2**24 − 1).
    - `seed`: non-negative integer choosing the shift of the m-sequence.
    - `temperature_c`: chamber temperature, °C.
    - `dt`: sample period, s.
    """
    call = "prbs_power"
    dt = _dt(call, dt)
    level = _finite(call, "level_w", level_w)
    bit = _positive(call, "bit_s", bit_s)
    max_bits = (1 << max(_LFSR_TAPS)) - 1
    if isinstance(n_bits, bool) or not isinstance(n_bits, (int, np.integer)) \
            or not 1 <= n_bits <= max_bits:
        raise InputError(f"`prbs_power(n_bits={n_bits!r})` must be an integer in "
                         f"1..{max_bits}.", field="n_bits")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"`prbs_power(seed={seed!r})` must be a non-negative integer.",
                         field="seed")
    bits = _lfsr_bits(int(n_bits), int(seed))
    b = _Builder(call, _finite(call, "temperature_c", temperature_c), dt)
    # consecutive equal bits form one run: one knot and one phase per run
    edges = np.flatnonzero(np.diff(bits)) + 1
    starts = np.concatenate([[0], edges])
    ends = np.concatenate([edges, [len(bits)]])
    for s, e in zip(starts.tolist(), ends.tolist()):
        on = bool(bits[s])
        b.power(level if on else 0.0)
        b.hold((e - s) * bit, kind="power_step" if on else "dwell")
    b.power(0.0)
    return b.build()


def concatenate(*profiles: Profile) -> Profile:
    """Join profiles end to start into one continuous record.

    Profile `i + 1` is shifted to start at the last time of profile `i`, and that
    shared time appears once. Temperatures must chain (the next profile starts at the
    temperature where the previous ends; insert `step_shock` or `ramp` otherwise). At
    the joining sample the later profile's power applies, because a sampled power holds
    over the interval that follows it. Phases are shifted along; `ts` is rebuilt as
    `k * dt`.

    **Arguments:**

    - `*profiles`: at least one `Profile`, all with the same `dt`.

    **Returns:** the joined `Profile`.
    """
    if not profiles:
        raise InputError("`concatenate()` needs at least one profile.")
    for i, p in enumerate(profiles):
        if not isinstance(p, Profile):
            raise InputError(f"`concatenate(...)` argument {i} is a {type(p).__name__}, "
                             "not a Profile.")
    dt = profiles[0].dt
    for i, p in enumerate(profiles[1:], start=1):
        if not math.isclose(p.dt, dt, rel_tol=1e-12, abs_tol=0.0):
            raise InputError(f"`concatenate(...)`: profile {i} has dt={p.dt:g} s but profile 0 "
                             f"has dt={dt:g} s; generate all segments with the same dt.",
                             field="dt")
    temps = [profiles[0].temperature]
    powers = [profiles[0].power]
    phases = list(profiles[0].phases)
    offset = len(profiles[0]) - 1
    for i, p in enumerate(profiles[1:], start=1):
        prev_end = temps[-1][-1]
        if abs(p.temperature[0] - prev_end) > 1e-9 * max(1.0, abs(prev_end)):
            raise InputError(
                f"`concatenate(...)`: profile {i} starts at {p.temperature[0]:g} °C but profile "
                f"{i - 1} ends at {prev_end:g} °C; segments must chain (insert a `step_shock` "
                "or a `ramp` between them).", field="temperature")
        # the joining sample: temperature equal, power from the later profile
        powers[-1] = powers[-1][:-1]
        temps.append(p.temperature[1:])
        powers.append(p.power)
        shift = offset * dt
        phases.extend(Phase(ph.start_s + shift, ph.end_s + shift, ph.kind) for ph in p.phases)
        offset += len(p) - 1
    ts = np.arange(offset + 1, dtype=np.float64) * dt
    return Profile(ts=ts, temperature=np.concatenate(temps), power=np.concatenate(powers),
                   phases=tuple(phases))


def calibration_schedule(dt: Real = 1.0, low_c: Real = -40.0, high_c: Real = 85.0,
                         rates_c_per_min: Sequence[Real] = (1.0, 5.0, 10.0),
                         dwell_s: Real = 1800.0, start_c: Real = 25.0,
                         soak_s: Real = 1800.0, end_c: Real | None = None) -> Profile:
    """The multi-phase thermal calibration profile.

    A soak at `start_c` for `soak_s`; a ramp to `low_c` at the first rate and a dwell
    there; then, for each rate in order, a ramp `low_c → high_c`, a dwell at `high_c`, a
    ramp `high_c → low_c` and a dwell at `low_c`. Every dwell lasts `dwell_s`. The
    profile ends at `low_c`, or at `end_c` if given (the last ramp goes there instead).

    **Arguments:**

    - `dt`: sample period, s.
    - `low_c`, `high_c`: dwell plateaus, °C, within the chamber range −55..+105 °C.
    - `rates_c_per_min`: ramp rates, °C/min (> 0).
    - `dwell_s`: plateau length, s (>= 0).
    - `start_c`: room temperature of the initial soak, °C (within the chamber range).
    - `soak_s`: initial soak length, s (>= 0).
    - `end_c`: temperature of the last ramp's end and final dwell, °C (within the
      chamber range; default `low_c`).
    """
    call = "calibration_schedule"
    dt = _dt(call, dt)
    low = _in_chamber(call, "low_c", low_c)
    high = _in_chamber(call, "high_c", high_c)
    start = _in_chamber(call, "start_c", start_c)
    if not low < high:
        raise InputError(f"`calibration_schedule(low_c={low_c!r}, high_c={high_c!r})` needs "
                         "low_c < high_c.", field="high_c")
    try:
        rates = [_positive(call, "rates_c_per_min", r) for r in rates_c_per_min]
    except TypeError:
        raise InputError(f"`calibration_schedule(rates_c_per_min={rates_c_per_min!r})` must be "
                         "a sequence of rates in °C/min.", field="rates_c_per_min") from None
    if not rates:
        raise InputError("`calibration_schedule(rates_c_per_min=())` needs at least one rate.",
                         field="rates_c_per_min")
    dwell_len = _nonnegative(call, "dwell_s", dwell_s)
    soak_len = _nonnegative(call, "soak_s", soak_s)
    end = low if end_c is None else _in_chamber(call, "end_c", end_c)
    b = _Builder(call, start, dt)
    b.hold(soak_len)
    b.ramp_to(low, rates[0])
    b.hold(dwell_len)
    for i, rate in enumerate(rates):
        b.ramp_to(high, rate)
        b.hold(dwell_len)
        b.ramp_to(end if i == len(rates) - 1 else low, rate)
        b.hold(dwell_len)
    return b.build()


def _ramp_cycle(rate_c_per_min: float) -> Callable[..., Profile]:
    def make(dt: Real = 1.0) -> Profile:
        b = _Builder(f"ramp{rate_c_per_min:g}", 25.0, _dt("builtin_profile", dt))
        b.hold(600.0)
        b.ramp_to(85.0, rate_c_per_min)
        b.hold(1800.0)
        b.ramp_to(25.0, rate_c_per_min)
        b.hold(1800.0)
        return b.build()

    make.__doc__ = (f"10 min soak at 25 °C, ramp to 85 °C at {rate_c_per_min:g} °C/min, "
                    "30 min dwell, ramp back to 25 °C, 30 min dwell.")
    return make


BUILTIN_PROFILES: dict[str, Callable[..., Profile]] = {
    "calibration": lambda dt=1.0: calibration_schedule(dt=dt),
    "ramp1": _ramp_cycle(1.0),
    "ramp5": _ramp_cycle(5.0),
    "ramp10": _ramp_cycle(10.0),
    "shock": lambda dt=1.0: step_shock(25.0, 85.0, before_s=600.0, after_s=3600.0, dt=dt),
    "viscoelastic_dwell": lambda dt=1.0: viscoelastic_dwell(dt=dt),
    "power_step": lambda dt=1.0: power_step(1.0, before_s=600.0, on_s=1800.0, after_s=1800.0,
                                            dt=dt),
    "prbs": lambda dt=1.0: prbs_power(1.0, bit_s=60.0, n_bits=127, seed=0, dt=dt),
    "eol_step": lambda dt=1.0: power_step(1.0, before_s=60.0, on_s=600.0, after_s=300.0,
                                          dt=dt),
    "eol_sweep": lambda dt=1.0: power_sweep(1.0, (300.0, 30.0), (2, 10), dt=dt),
}
"""Named profiles, each `f(dt=1.0) -> Profile`.

- `"calibration"`: `calibration_schedule()` (−40..85 °C at 1, 5, 10 °C/min).
- `"ramp1"`, `"ramp5"`, `"ramp10"`: 10 min at 25 °C, ramp to 85 °C, 30 min, ramp back
  to 25 °C, 30 min.
- `"shock"`: 10 min at 25 °C, step to 85 °C, 1 h there.
- `"viscoelastic_dwell"`: `viscoelastic_dwell()` (10 min at 25 °C, step to 85 °C, 3 h).
- `"power_step"`: 1 W for 30 min after 10 min off, then 30 min off, at 25 °C.
- `"prbs"`: 127 bits of 60 s, 0 or 1 W, at 25 °C.
- `"eol_step"`: the end-of-line single-point dynamic test: 1 W for 10 min after 1 min off,
  then 5 min off, at 25 °C (16 min).
- `"eol_sweep"`: the end-of-line two-point frequency test: `power_sweep` of 1 W peak,
  2 cycles of 300 s then 10 of 30 s, at 25 °C (15 min).
"""


def builtin_profile(name: str, dt: Real = 1.0) -> Profile:
    """Build the named entry of `BUILTIN_PROFILES` at sample period `dt` (s)."""
    try:
        make = BUILTIN_PROFILES[name]
    except (KeyError, TypeError):
        raise InputError(f"unknown profile {name!r}; expected one of "
                         f"{', '.join(sorted(BUILTIN_PROFILES))}.", field="profile") from None
    return make(dt=dt)
