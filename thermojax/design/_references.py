"""The profiles a design is measured against, of the same length and sample period.

- `prbs`: a pseudo-random binary sequence of power (`measurements.prbs_power`, 60 s
  bits) between the power limits, the chamber held at the start temperature.
- `calibration`: the packaged calibration schedule (−40..85 °C plateaus at 1, 5 and
  10 °C/min, `measurements._profiles.calibration_schedule`) compressed uniformly in time to
  the duration (every rate scales with it), its plateaus clipped to the temperature
  limits, the power held at the middle of the power limits (the unit dissipating as in
  service; with no power at all the common scale of every capacitance and conductance
  is left undetermined).

A reference is not held to the ramp limit: a compressed schedule may ramp faster than
the design may, which only favours the reference; the report says so
(`ChamberLimits.violations`).
"""

from __future__ import annotations

import numpy as np

from ..measurements._profiles import calibration_schedule, prbs_power
from ._schedule import ProfileSchedule

REFERENCES = ("calibration", "prbs")

#: s, bit length of the reference PRBS (that of the built-in `prbs` profile).
PRBS_BIT_S = 60.0


def reference_profile(name: str, schedule: ProfileSchedule) -> tuple[np.ndarray, np.ndarray]:
    """`(chamber °C, power W)` (times,) each, of the named reference on the schedule's
    samples; the chamber air through the chamber's settling (`ChamberLimits.settling_s`),
    as the design's."""
    T, P = _programmed(name, schedule)
    if schedule.limits.settling_s > 0:
        import jax.numpy as jnp

        from ._schedule import settle

        T = np.asarray(settle(jnp.asarray(T), schedule.dt, schedule.limits.settling_s))
    return T, P


def reference_inputs(name: str, schedule: ProfileSchedule, spec) -> tuple[np.ndarray,
                                                                         np.ndarray]:
    """`reference_profile` for a model `spec`: a column the model does not have is held at
    the start (the chamber at `start_c` without a boundary, the power at
    `start_power_w` without a heat input)."""
    T, P = reference_profile(name, schedule)
    if not spec.boundary_columns:
        T = np.full_like(T, schedule.limits.start_c)
    if not spec.heat_columns:
        P = np.full_like(P, schedule.limits.start_power_w)
    return T, P


def _programmed(name: str, schedule: ProfileSchedule) -> tuple[np.ndarray, np.ndarray]:
    ts, lim = schedule.ts, schedule.limits
    plo, phi = lim.power_w
    if name == "prbs":
        n_bits = max(1, int(np.ceil(schedule.duration_s / PRBS_BIT_S)))
        prof = prbs_power(1.0, PRBS_BIT_S, n_bits, 0, temperature_c=lim.start_c, dt=1.0)
        # the 1 s record's sample at or before each time (power is held)
        bits = np.asarray(prof.power)[np.clip(np.floor(ts + 1e-9).astype(int), 0,
                                              len(prof.power) - 1)]
        return np.full(ts.shape, lim.start_c), plo + (phi - plo) * bits
    if name == "calibration":
        cal = calibration_schedule(dt=1.0)
        scale = cal.duration / schedule.duration_s
        lo, hi = lim.temperature_c
        T = np.clip(np.interp(ts * scale, cal.ts, cal.temperature), lo, hi)
        return T, np.full(ts.shape, 0.5 * (plo + phi))
    raise ValueError(f"unknown reference {name!r}; expected one of {REFERENCES}.")


def prbs_start(schedule: ProfileSchedule) -> np.ndarray:
    """Schedule numbers (K + M,) of the reference PRBS: the chamber still, each power level
    at the PRBS's bit at its middle (within 0.25 % of a power limit). A search started here
    ends no worse than the PRBS by its own criterion (to that 0.25 %, when the power levels
    are as long as its bits)."""
    z = np.zeros(schedule.n_parameters)
    M = schedule.power_segments
    if M:
        _, P = reference_profile("prbs", schedule)
        mid = 0.5 * (schedule.power_times[:-1] + schedule.power_times[1:])
        held = P[np.clip(np.searchsorted(schedule.ts, mid, side="right") - 1, 0, len(P) - 1)]
        on = held > 0.5 * sum(schedule.limits.power_w)
        z[schedule.temperature_segments:] = np.where(on, 6.0, -6.0)
    return z
