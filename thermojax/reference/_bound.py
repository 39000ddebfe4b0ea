"""A derived bound on the distance between the fixed-point and the exact observer.

With `x̃` the fixed-point observer (decoded, offset coordinates) and `x̂` the exact one
(float64 matrices, unquantized data), the error `e = x̃ - x̂` obeys

    e[k] = A_e e[k-1] + w[k],        A_e = (I - L C) Phi,

    w = (I - L C) [δPhi x̃[k-1] + δB0 ũ[k-1] + B0 δu[k-1] + δB1 ũ[k] + B1 δu[k] + ε_pred]
        + L [δy - δC x̃⁻ - δD ũ[k] - D δu[k] - ε_out] + δL r̃ + ε_corr,

where `δM` is a coefficient's quantization error, `δu`, `δy` the data's (half an input or
state LSB), and each `ε` one rounding (at most half a state LSB). Taking absolute values
entry by entry with envelopes `|x̃| <= X`, `|x̃⁻| <= X⁻`, `|ũ| <= U`, `|r̃| <= R` gives
`|w| <= w̄`, and then for every `k`

    |e[k]| <= S (w̄ + ē0),    S = Σ_{j>=0} |A_e^j|,

with `ē0` the bound of the first step's error (the encoded `x0` corrected once). `S` is a
geometric series: with `J` such that `‖A_e^J‖∞ <= 1/2`,
`S <= (I - |A_e^J|)^{-1} Σ_{j<J} |A_e^j|` (entrywise, since `|A_e^{j+J}| <= |A_e^J| |A_e^j|`).

The bound holds while no value saturates and the envelopes hold: a playback checks both.
It covers the fault-free observer (all sensors in use).
"""

from __future__ import annotations

import dataclasses

import numpy as np


def error_series(A: np.ndarray, max_power: int = 1 << 22) -> tuple[np.ndarray, int]:
    """Entrywise upper bound `S >= Σ_{j>=0} |A^j|` and the `J` used (see module doc)."""
    n = A.shape[0]
    P, Aj, partial = np.eye(n), np.eye(n), np.zeros((n, n))
    J = 0
    while True:
        partial += np.abs(Aj)
        Aj = Aj @ A
        J += 1
        if np.abs(Aj).sum(axis=1).max() <= 0.5:
            break
        if J >= max_power:
            raise ValueError(f"`error_series`: ‖A^j‖ still above 1/2 after {J} powers; the "
                             f"error dynamics are not (usefully) stable.")
    del P
    return np.linalg.solve(np.eye(n) - np.abs(Aj), partial), J


@dataclasses.dataclass(frozen=True)
class ErrorBound:
    """`bound (n,)` in kelvin per state; `w` the per-step disturbance bound; `series` the
    `S` matrix; `J` its power; `parts` the bound split into its sources (coefficients,
    data, rounding), each also in kelvin per state."""

    bound: np.ndarray
    w: np.ndarray
    series: np.ndarray
    J: int
    parts: dict


def quantization_error_bound(fixed, x_env, xm_env, u_env, r_env) -> ErrorBound:
    """The bound of the module doc for a `FixedObserver`, all sensors in use.

    **Arguments:** envelopes in physical units, offset coordinates: `x_env (n,)` of the
    corrected states, `xm_env (n,)` of the predicted ones, `u_env (m,)` of the inputs
    (minus their offsets), `r_env (p,)` of the residuals.
    """
    s = fixed.system
    n = s.n_states
    L, C, D = s.L, s.C, s.D
    mask = s.full_mask
    dE = fixed.coef_error
    dL = dE["L"][mask]
    ILC = np.abs(np.eye(n) - L @ C)
    q2 = fixed.lsb / 2
    du = fixed.u_scale * 2.0 ** -fixed.fmt.frac_bits / 2
    x_env, xm_env, u_env, r_env = (np.asarray(v, float) for v in (x_env, xm_env, u_env, r_env))
    coef = ILC @ (np.abs(dE["Phi"]) @ x_env + np.abs(dE["B0"]) @ u_env
                  + np.abs(dE["B1"]) @ u_env) \
        + np.abs(L) @ (np.abs(dE["C"]) @ xm_env + np.abs(dE["D"]) @ u_env) + np.abs(dL) @ r_env
    data = ILC @ ((np.abs(s.B0) + np.abs(s.B1)) @ du) \
        + np.abs(L) @ (np.full(s.n_outputs, q2) + np.abs(D) @ du)
    rounding = ILC @ np.full(n, q2) + np.abs(L) @ np.full(s.n_outputs, q2) + q2
    # first step: encoded x0 (half an LSB), then one correction
    e0 = ILC @ np.full(n, q2) + np.abs(L) @ (np.full(s.n_outputs, 2 * q2)
                                             + np.abs(D) @ du + np.abs(dE["C"]) @ xm_env
                                             + np.abs(dE["D"]) @ u_env) \
        + np.abs(dL) @ r_env + q2
    S, J = error_series(s.error_dynamics())
    w = coef + data + rounding
    parts = {"coefficients": S @ coef, "data": S @ data, "rounding": S @ rounding,
             "initial": S @ e0}
    return ErrorBound(S @ (w + e0), w, S, J, parts)
