"""Figures of an observer's response: rise time and noise amplification."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg


def rise_time(ts, signal, initial: float, final: float, fraction: float = 0.9) -> float:
    """The first time `signal` reaches `initial + fraction (final − initial)`.

    Linear interpolation between the two samples around the crossing.

    **Arguments:**

    - `ts`: sample times (s), shape (times,), increasing.
    - `signal`: the response, shape (times,).
    - `initial`, `final`: the step's start and end values.
    - `fraction`: default 0.9 (the 90 % time).

    **Returns:** the time (s) in the units of `ts`, or `inf` if never reached.
    """
    ts, x = np.asarray(ts, float), np.asarray(signal, float)
    level = initial + fraction * (final - initial)
    s = np.sign(final - initial)
    above = np.flatnonzero(s * (x - level) >= 0)
    if above.size == 0:
        return math.inf
    k = int(above[0])
    if k == 0:
        return float(ts[0])
    x0, x1 = x[k - 1], x[k]
    return float(ts[k - 1] + (level - x0) / (x1 - x0) * (ts[k] - ts[k - 1]))


def estimate_noise_std(observer, noise) -> np.ndarray:
    """Steady-state std of each state estimate caused by white sensor noise alone.

    The noise part `ξ` of the estimate obeys `ξ[k] = (I − L C) Phi ξ[k−1] + L v[k]`
    (`run_observer`'s filter form), so its covariance solves the discrete Lyapunov
    equation `S = F S Fᵀ + L R Lᵀ`, `F = (I − L C) Phi`, `R = diag(noise²)`.
    Divide by the noise std for the noise amplification.

    **Arguments:**

    - `observer`: an `Observer`.
    - `noise`: sensor noise std (°C), a scalar or one per output.

    **Returns:** std per state (°C), shape (states,).
    """
    Phi = np.asarray(observer.system.Phi, float)
    C = np.asarray(observer.system.C, float)
    L = np.asarray(observer.gain, float)
    r = np.broadcast_to(np.asarray(noise, float), (C.shape[0],))
    F = Phi - L @ C @ Phi
    if np.max(np.abs(np.linalg.eigvals(F))) >= 1.0:
        raise ValueError("`estimate_noise_std`: the observer's error dynamics are unstable "
                         "(a pole on or outside the unit circle); no steady state exists.")
    S = scipy.linalg.solve_discrete_lyapunov(F, (L * r[None, :] ** 2) @ L.T)
    return np.sqrt(np.maximum(np.diag(S), 0.0))
