"""The first-order lag `dy/dt = (x − y)/τ` of sampled signals (NumPy and SciPy only).

One filter serves the viscoelastic strain of a bias channel (`fitting._bias`) and
the lagged score directions of candidate effects (`investigation._candidates`).
"""

from __future__ import annotations

import numpy as np


def first_order_lag(x: np.ndarray, dt, tau: float) -> np.ndarray:
    """First-order lag `y` of `x`: `dy/dt = (x − y)/τ`, at rest at the first sample
    (`y[0] = x[0]`).

    Exact for `x` linear between samples (first-order hold). With `r = dt/τ`,
    `a = exp(−r)` and `β = (1 − a)/r`,

        y[k+1] = a y[k] + (1 − β) x[k+1] + (β − a) x[k],

    where `1 − a = −expm1(−r)` keeps every digit when `dt ≪ τ` (the form
    `(τ/dt)(1 − a)` cancels catastrophically there).

    **Arguments:**

    - `x`: the signal, shape `(times, ...)`, filtered along axis 0, any unit.
    - `dt`: sample period, s: a scalar for uniform sampling, or the steps
      `np.diff(ts)`, shape `(times − 1,)` (jitter and gaps are exact as well).
    - `tau`: time constant, s, > 0.

    **Returns:** `y`, same shape and unit as `x`, float64.
    """
    import scipy.signal  # where used: it costs every command's start 0.6 s

    x = np.asarray(x, dtype=float)
    if x.shape[0] < 2:
        return x.copy()
    steps = np.broadcast_to(np.asarray(dt, dtype=float), (x.shape[0] - 1,))
    r = steps / tau
    one_minus_a = -np.expm1(-r)
    a = 1.0 - one_minus_a
    beta = one_minus_a / r
    b0, b1 = 1.0 - beta, beta - a
    dev = x - x[:1]  # y − x[0] starts at 0: the filter starts at rest
    if np.ptp(steps) <= 1e-9 * steps.mean():  # uniform sampling: one linear filter
        out = scipy.signal.lfilter([b0[0], b1[0]], [1.0, -a[0]], dev, axis=0)
    else:  # jitter or gaps: the same recursion step by step (still exact)
        out = np.zeros_like(dev)
        for k in range(steps.size):
            out[k + 1] = a[k] * out[k] + b0[k] * dev[k + 1] + b1[k] * dev[k]
    return out + x[:1]
