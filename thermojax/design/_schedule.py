"""A chamber profile as a few numbers: temperature knots and power levels, always inside
the limits.

The chamber air temperature is piecewise linear through `K + 1` knots at
`t_k = k · duration / K`; the first is the start temperature. Each further knot is
chosen inside the interval the limits leave it,

    T_(k+1) = T_k + lo_k + (hi_k − lo_k) · σ(z_k),
    lo_k = max(−r Δ, T_min − T_k),   hi_k = min(r Δ, T_max − T_k),

(`r` the ramp rate, `Δ` the knot spacing, `σ` the logistic function), so every knot is
in range and every ramp within the rate for any real `z`: the search needs no
constraints. Between knots the samples lie on the line, so two samples `dt` apart
differ by at most `r · dt`. Power is piecewise constant over `M` equal segments,
`P_j = P_min + (P_max − P_min) · σ(w_j)`, held over each sample (zero-order hold); the
first sample period keeps the start power, so the unit's start, at rest at the first
sample's inputs, is the same for every design. The map from `(z, w)` to the sampled
inputs is smooth, and JAX differentiates through it.

A chamber that settles with its own time constant `τ` (`ChamberLimits.settling_s`) is
programmed with that line as its setpoint; the air the unit sees follows it through a
first-order lag, exactly for a setpoint linear between samples,

    T_air[k+1] = a T_air[k] + (1 − a) T_set[k] + s_k (dt − τ (1 − a)),   a = e^(−dt/τ),

`s_k` the setpoint's slope, from rest at the start. The lag's impulse response is
positive with unit area, so the air stays inside the range and within the ramp rate
that the setpoint keeps.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError
from ._limits import ChamberLimits


@dataclass(frozen=True)
class ProfileSchedule:
    """How a designed profile is described and sampled.

    **Arguments:**

    - `duration_s`: length, s (a whole number of `dt`).
    - `dt`: sample period, s.
    - `limits`: the `ChamberLimits`.
    - `temperature_segments`: `K`, ramps between knots (0: the chamber stays at the start).
    - `power_segments`: `M`, power levels (0: the power stays at the start power).
    """

    duration_s: float
    dt: float
    limits: ChamberLimits
    temperature_segments: int = 24
    power_segments: int = 96

    def __post_init__(self):
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise InputError(f"the sample period {self.dt!r} s must be > 0.", field="--dt")
        n = self.duration_s / self.dt
        if not (np.isfinite(n) and n >= 2):
            raise InputError(f"the duration {self.duration_s:g} s must hold at least two "
                             f"sample periods of {self.dt:g} s.", field="--duration")
        if abs(n - round(n)) > 1e-9 * max(n, 1.0):
            raise InputError(f"the duration {self.duration_s:g} s is not a whole number of "
                             f"sample periods ({self.dt:g} s).", field="--duration")
        for name, k, flag in (("temperature", self.temperature_segments, "--knots"),
                              ("power", self.power_segments, "--power-steps")):
            if k < 0 or k > round(n):
                raise InputError(f"{k} {name} segments do not fit {round(n)} sample periods; "
                                 f"use 0..{round(n)}.", field=flag)

    @property
    def n_times(self) -> int:
        return int(round(self.duration_s / self.dt)) + 1

    @property
    def ts(self) -> np.ndarray:
        """Sample times, s, (times,)."""
        return np.arange(self.n_times) * self.dt

    @property
    def n_parameters(self) -> int:
        return self.temperature_segments + self.power_segments

    @property
    def knot_times(self) -> np.ndarray:
        """Times of the temperature knots, s, (K + 1,)."""
        return np.linspace(0.0, self.duration_s, self.temperature_segments + 1)

    @property
    def power_times(self) -> np.ndarray:
        """Segment boundaries of the power levels, s, (M + 1,)."""
        return np.linspace(0.0, self.duration_s, self.power_segments + 1)

    def knots(self, params):
        """Temperature knots (K + 1,), °C, and power levels (M,), W, of `params` (K + M,)."""
        K = self.temperature_segments
        lim = self.limits
        lo_c, hi_c = lim.temperature_c
        step = lim.ramp_c_per_min / 60.0 * (self.duration_s / max(K, 1))

        def move(T, z):
            lo = jnp.maximum(-step, lo_c - T)
            hi = jnp.minimum(step, hi_c - T)
            T = T + lo + (hi - lo) * jax.nn.sigmoid(z)
            return T, T

        start = jnp.asarray(lim.start_c, params.dtype)
        _, rest = jax.lax.scan(move, start, params[:K])
        knots = jnp.concatenate([start[None], rest])
        plo, phi = lim.power_w
        levels = plo + (phi - plo) * jax.nn.sigmoid(params[K:])
        return knots, levels

    def setpoint(self, params):
        """The programmed chamber temperature (times,), °C, of `params` (K + M,)."""
        knots, _ = self.knots(params)
        ts = jnp.asarray(self.ts, params.dtype)
        if self.temperature_segments:
            return jnp.interp(ts, jnp.asarray(self.knot_times, params.dtype), knots)
        return jnp.full(ts.shape, self.limits.start_c, params.dtype)

    def sampled(self, params):
        """Chamber air temperature (times,), °C, and power (times,), W, of `params` (K + M,)."""
        knots, levels = self.knots(params)
        ts = jnp.asarray(self.ts, params.dtype)
        temperature = self.setpoint(params)
        tau = self.limits.settling_s
        if tau > 0:
            temperature = settle(temperature, self.dt, tau)
        if self.power_segments:
            seg = np.clip(np.floor(self.ts / (self.duration_s / self.power_segments) + 1e-9),
                          0, self.power_segments - 1).astype(int)
            power = levels[seg].at[0].set(self.limits.start_power_w)
        else:
            power = jnp.full(ts.shape, self.limits.start_power_w, params.dtype)
        return temperature, power

    def describe(self, params) -> dict:
        """The design as a chamber controller reads it: knots `[t s, T °C]` and power
        segments `[start s, end s, P W]`."""
        knots, levels = (np.asarray(a) for a in self.knots(jnp.asarray(params)))
        pt = self.power_times
        return {"temperature_knots": [[float(t), float(T)] for t, T in
                                      zip(self.knot_times, knots)],
                "knots_are": ("setpoints, the air following with the chamber's settling time"
                              if self.limits.settling_s > 0 else "the air temperature"),
                "power_segments": [[float(pt[j]), float(pt[j + 1]), float(levels[j])]
                                   for j in range(self.power_segments)],
                "start_power_w": self.limits.start_power_w}


ProfileSchedule.__init__.__doc__ = ProfileSchedule.__doc__


def settle(setpoint, dt: float, tau: float):
    """The air temperature (times,) of a chamber with time constant `tau` (s) following
    `setpoint` (times,), °C, linear between samples `dt` apart, from rest at the first."""
    a = float(np.exp(-dt / tau))
    slopes = jnp.diff(setpoint) / dt

    def step(y, inputs):
        u, s = inputs
        y = a * y + (1.0 - a) * u + s * (dt - tau * (1.0 - a))
        return y, y

    _, rest = jax.lax.scan(step, setpoint[0], (setpoint[:-1], slopes))
    return jnp.concatenate([setpoint[:1], rest])

