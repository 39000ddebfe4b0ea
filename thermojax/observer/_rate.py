"""Which observer rate is enough, and what an anti-alias filter costs.

The rule of thumb: sample at 8–15 times the highest closed-loop bandwidth. Here the
rule is checked against the observer itself. The sensor noise is taken as white with a
fixed density: `noise` (°C) is the std of one sample at `noise_rate_hz`, so a sample at
rate `f` has std `noise · sqrt(f / noise_rate_hz)` (an ADC averaging over its own
period, filtered by its anti-alias filter to half the rate). The error that matters is
the largest in a sample period, just before the next reading (the predicted covariance
`P⁻`): it falls with the rate towards the continuous-time (Kalman–Bucy) limit, and the
rate that is *enough* is the lowest whose worst-state error std is within `tolerance`
(10 %) of that limit. The closed-loop
bandwidth is that of the limit, `max |eig(A − K C)| / 2π` Hz.

An anti-alias filter (Butterworth, `order`, cutoff `fc` Hz) delays every reading by its
group delay `τ_g` at low frequency. During a ramp of `ramp_C_per_s` the readings lag by
`ramp · τ_g` and the observer, designed without the filter, turns that into a steady
error `(I − A_e)⁻¹ L (ramp · τ_g · 1)`, `A_e = (I − L C) Phi`, compared with its own
error std.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Hz, the candidate rates (1-2-5 steps).
DEFAULT_RATES = tuple(float(a * 10.0 ** k) for k in range(-2, 4) for a in (1, 2, 5))


@dataclasses.dataclass(frozen=True)
class RateRow:
    """One candidate rate: `rate_hz`, the worst state's steady-state error std (°C,
    `error_std`) and its ratio to the continuous limit, `rate_over_bandwidth`, and
    whether the sampled sensors still observe every state (`export` refuses a rate
    that loses one)."""

    rate_hz: float
    error_std: float
    error_ratio: float
    rate_over_bandwidth: float
    observable: bool


@dataclasses.dataclass(frozen=True)
class RateAdvice:
    """`rows` per candidate rate; `limit_std` (°C) the continuous-time worst-state error
    std; `bandwidth_hz` the continuous observer's highest closed-loop bandwidth;
    `recommended_hz` the lowest observable candidate within `tolerance` of the limit
    (None if none);
    `rule_hz` the rule of thumb's 8–15× range; `states` the names; `worst_state` the state the
    error std is of."""

    rows: tuple
    limit_std: float
    bandwidth_hz: float
    recommended_hz: float | None
    rule_hz: tuple[float, float]
    tolerance: float
    worst_state: str


@dataclasses.dataclass(frozen=True)
class FilterCost:
    """An anti-alias filter at `rate_hz`: `group_delay_s` at low frequency, and the
    steady error it adds to each state during a ramp (`ramp_error (n,)`, °C), with the
    observer's own error std per state (`error_std (n,)`) for scale."""

    order: int
    cutoff_hz: float
    rate_hz: float
    group_delay_s: float
    ramp_C_per_s: float
    ramp_error: np.ndarray
    error_std: np.ndarray


def _matrices(model, sensors):
    system = model.linear_system()
    rows = list(range(system.C.shape[0])) if sensors is None else list(sensors)
    A = np.asarray(system.A, float)
    C = np.asarray(system.C, float)[rows]
    q = np.asarray(model.process_noise, float)
    r = np.asarray(model.noise, float)[rows]
    return system, A, C, q, r


def _discrete_kalman(system, A, C, q, r2, dt):
    """`(Phi, L, predicted covariance)` of the steady-state Kalman filter at `dt`."""
    import equinox as eqx
    import jax.numpy as jnp

    from ..dynamics._discretize import discretize
    from ._kalman import discrete_process_covariance, steady_state_kalman

    sub = eqx.tree_at(lambda s: s.C, system, jnp.asarray(C))
    d = discretize(sub, dt)
    k = steady_state_kalman(d, discrete_process_covariance(A, q, dt), r2)
    return (np.asarray(d.Phi, float), np.asarray(k.gain, float),
            np.asarray(k.predicted_covariance), d)


def rate_advice(model, sensors=None, rates=DEFAULT_RATES, noise_rate_hz: float = 1.0,
                tolerance: float = 0.1) -> RateAdvice:
    """The error of the steady-state Kalman observer at each of `rates` (Hz) against the
    continuous-time limit (see the module docstring). `sensors`: row indices of the
    sensors used (default all)."""
    import scipy.linalg

    from ._observability import observability_rank

    system, A, C, q, r = _matrices(model, sensors)
    density = r ** 2 / noise_rate_hz                  # °C² s, per sensor
    Pc = scipy.linalg.solve_continuous_are(A.T, C.T, np.diag(q ** 2), np.diag(density))
    K = Pc @ C.T @ np.diag(1.0 / density)
    limit = np.sqrt(np.diag(Pc))
    worst = int(np.argmax(limit))
    bandwidth = float(np.abs(np.linalg.eigvals(A - K @ C)).max() / (2 * np.pi))
    rows = []
    for f in sorted(rates):
        _, _, P, d = _discrete_kalman(system, A, C, q, density * f, 1.0 / f)
        std = float(np.sqrt(max(P[worst, worst], 0.0)))
        rows.append(RateRow(float(f), std, std / limit[worst], float(f) / bandwidth,
                            observability_rank(d) == A.shape[0]))
    enough = [row.rate_hz for row in rows
              if row.error_ratio <= 1.0 + tolerance and row.observable]
    names = model.network.topology.node_names
    return RateAdvice(tuple(rows), float(limit[worst]), bandwidth,
                      enough[0] if enough else None, (8 * bandwidth, 15 * bandwidth),
                      tolerance, names[worst])


def butterworth_group_delay(order: int, cutoff_hz: float) -> float:
    """Group delay at low frequency (s) of an analog Butterworth low-pass filter."""
    import scipy.signal

    b, a = scipy.signal.butter(order, 2 * np.pi * cutoff_hz, analog=True)
    # τ_g(0) = a1/a0 − b1/b0 for H = B/A (coefficients in ascending powers of s)
    a_asc, b_asc = a[::-1], b[::-1]
    b1 = b_asc[1] if b_asc.size > 1 else 0.0
    return float(a_asc[1] / a_asc[0] - b1 / b_asc[0])


def anti_alias_cost(model, rate_hz: float, order: int, cutoff_hz: float, sensors=None,
                    ramp_C_per_s: float = 5.0 / 60.0, noise_rate_hz: float = 1.0) -> FilterCost:
    """The steady error an anti-alias filter's delay adds during a ramp (module docstring)."""
    system, A, C, q, r = _matrices(model, sensors)
    dt = 1.0 / rate_hz
    Phi, L, P, _ = _discrete_kalman(system, A, C, q, r ** 2 / noise_rate_hz * rate_hz, dt)
    tau = butterworth_group_delay(order, cutoff_hz)
    n = Phi.shape[0]
    Ae = (np.eye(n) - L @ C) @ Phi
    bias = ramp_C_per_s * tau * np.ones(C.shape[0])   # every reading lags the ramp
    err = np.linalg.solve(np.eye(n) - Ae, L @ bias)
    return FilterCost(int(order), float(cutoff_hz), float(rate_hz), tau, float(ramp_C_per_s),
                      np.abs(err), np.sqrt(np.maximum(np.diag(P), 0.0)))
