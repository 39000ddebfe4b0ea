"""What the chamber and the unit's heater can do: the box every designed profile stays in."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .._errors import InputError
from ..measurements._profiles import CHAMBER_MAX_C, CHAMBER_MIN_C


@dataclass(frozen=True)
class ChamberLimits:
    """The limits a designed chamber profile respects at every sample.

    **Arguments:**

    - `temperature_c`: `(low, high)` chamber air temperature, °C, inside the chamber's
      envelope −55..+105 °C.
    - `ramp_c_per_min`: the fastest chamber change, °C/min (> 0): two samples `dt` apart
      differ by at most `ramp_c_per_min · dt / 60`.
    - `power_w`: `(low, high)` power of every heat input, W.
    - `start_c`: chamber temperature at the first sample, °C (inside `temperature_c`);
      the unit starts at rest there.
    - `start_power_w`: power over the first sample period, W (inside `power_w`; default
      `power_w[0]`).
    - `settling_s`: the chamber's own time constant, s (>= 0): the air follows the
      programmed setpoint through a first-order lag (0: the air is the setpoint).
    """

    temperature_c: tuple[float, float] = (-40.0, 85.0)
    ramp_c_per_min: float = 10.0
    power_w: tuple[float, float] = (0.0, 1.0)
    start_c: float = 25.0
    start_power_w: float | None = None
    settling_s: float = 0.0

    def __post_init__(self):
        lo, hi = (float(v) for v in self.temperature_c)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise InputError(f"the temperature range {lo:g}..{hi:g} °C needs finite LOW < HIGH.",
                             field="--temperature-range")
        if lo < CHAMBER_MIN_C or hi > CHAMBER_MAX_C:
            raise InputError(f"the temperature range {lo:g}..{hi:g} °C leaves the chamber's "
                             f"envelope {CHAMBER_MIN_C:g}..{CHAMBER_MAX_C:g} °C.",
                             field="--temperature-range")
        rate = float(self.ramp_c_per_min)
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"the ramp rate {rate:g} °C/min must be a finite number > 0.",
                             field="--ramp-rate")
        plo, phi = (float(v) for v in self.power_w)
        if not (math.isfinite(plo) and math.isfinite(phi) and plo <= phi):
            raise InputError(f"the power range {plo:g}..{phi:g} W needs finite LOW <= HIGH.",
                             field="--power-range")
        start = float(self.start_c)
        if not (math.isfinite(start) and lo <= start <= hi):
            raise InputError(f"the start temperature {start:g} °C is outside the temperature "
                             f"range {lo:g}..{hi:g} °C.", field="--start")
        p0 = plo if self.start_power_w is None else float(self.start_power_w)
        if not (math.isfinite(p0) and plo <= p0 <= phi):
            raise InputError(f"the start power {p0:g} W is outside the power range "
                             f"{plo:g}..{phi:g} W.", field="--start-power")
        settling = float(self.settling_s)
        if not (math.isfinite(settling) and settling >= 0):
            raise InputError(f"the chamber settling time {settling:g} s must be a finite "
                             "number >= 0.", field="--chamber-settling")
        object.__setattr__(self, "settling_s", settling)
        object.__setattr__(self, "temperature_c", (lo, hi))
        object.__setattr__(self, "ramp_c_per_min", rate)
        object.__setattr__(self, "power_w", (plo, phi))
        object.__setattr__(self, "start_c", start)
        object.__setattr__(self, "start_power_w", p0)

    def to_json(self) -> dict:
        return {"temperature_c": list(self.temperature_c), "ramp_c_per_min": self.ramp_c_per_min,
                "power_w": list(self.power_w), "start_c": self.start_c,
                "start_power_w": self.start_power_w, "settling_s": self.settling_s}

    def violations(self, ts, temperature, power, tolerance: float = 1e-9) -> list[str]:
        """Where a sampled profile (`ts` s, `temperature` °C, `power` W, each (times,))
        leaves the limits, in words; empty when it keeps them at every sample."""
        import numpy as np

        ts, T, P = (np.asarray(a, float) for a in (ts, temperature, power))
        out = []
        lo, hi = self.temperature_c
        tol = tolerance * max(1.0, abs(lo), abs(hi))
        if T.min() < lo - tol or T.max() > hi + tol:
            out.append(f"chamber {T.min():.4g}..{T.max():.4g} °C outside {lo:g}..{hi:g} °C")
        rate = np.abs(np.diff(T)) / np.diff(ts) * 60.0
        if rate.size and rate.max() > self.ramp_c_per_min * (1 + 1e-9) + tol:
            out.append(f"chamber changes at up to {rate.max():.4g} °C/min, over "
                       f"{self.ramp_c_per_min:g} °C/min")
        plo, phi = self.power_w
        ptol = tolerance * max(1.0, abs(plo), abs(phi))
        if P.size and (P.min() < plo - ptol or P.max() > phi + ptol):
            out.append(f"power {P.min():.4g}..{P.max():.4g} W outside {plo:g}..{phi:g} W")
        return out
