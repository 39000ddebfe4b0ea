"""The steady-state Kalman gain from the discrete algebraic Riccati equation.

Model: `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1] + w[k]`, `w ~ N(0, Qd)`, and
`y[k] = C x[k] + D u[k] + v[k]`, `v ~ N(0, R)`. The predicted covariance
`P = Cov(x[k] − x̂⁻[k])` in steady state solves the DARE

    P = Phi P Phiᵀ − Phi P Cᵀ (C P Cᵀ + R)⁻¹ C P Phiᵀ + Qd,

(`scipy.linalg.solve_discrete_are(Phiᵀ, Cᵀ, Qd, R)`), and the filter-form gain of
`Observer` is `L = P Cᵀ (C P Cᵀ + R)⁻¹` (MATLAB's "innovation gain" `M`; the predictor
gain of `control.dlqe` is `Phi L`). The filtered covariance is `(I − L C) P`.

`Qd` comes from a continuous diffusion `dx = ... dt + dβ`, `E[dβ dβᵀ] = Qc dt`, with
`Qc = diag(q²)` from each node's `process_noise` `q` (°C/√s), discretized exactly by
Van Loan (`thermojax.dynamics.discretize_process_noise`); `R = diag(noise²)` from the
sensors' `noise` (°C). Defaults when a model file gives none: `q = 1e-3 °C/√s`,
`noise = 0.01 °C` (`ThermalModel`'s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .._errors import InputError


@dataclass(frozen=True)
class KalmanGain:
    """The steady-state Kalman filter of a sampled system.

    - `gain`: filter-form `L = P Cᵀ (C P Cᵀ + R)⁻¹`, shape (states, outputs).
    - `predicted_covariance`: `P = Cov(x − x̂⁻)` (°C²), shape (states, states).
    - `filtered_covariance`: `(I − L C) P` (°C²), the covariance of `x − x̂`.
    """

    gain: np.ndarray
    predicted_covariance: np.ndarray
    filtered_covariance: np.ndarray

    @property
    def std(self) -> np.ndarray:
        """Steady-state std of each state's filtered estimate (°C)."""
        return np.sqrt(np.maximum(np.diag(self.filtered_covariance), 0.0))


def steady_state_kalman(system, process_covariance, measurement_covariance) -> KalmanGain:
    """The steady-state (filter-form) Kalman gain of a `DiscreteSystem`.

    **Arguments:**

    - `system`: the `DiscreteSystem` at the observer rate (`Phi`, `C`).
    - `process_covariance`: `Qd`, the covariance of the one-step process noise (°C²),
      shape (states, states), symmetric positive semidefinite
      (`discrete_process_covariance`).
    - `measurement_covariance`: `R` (°C²), shape (outputs, outputs) positive definite,
      or a vector of variances (outputs,).

    **Returns:** a `KalmanGain`.

    **Raises:** `InputError` when the shapes disagree or the Riccati equation has no
    stabilizing solution (the sensors leave a non-decaying mode unobservable).
    """
    Phi, C = np.asarray(system.Phi, float), np.asarray(system.C, float)
    n, p = Phi.shape[0], C.shape[0]
    Qd = np.asarray(process_covariance, float)
    R = np.asarray(measurement_covariance, float)
    if R.ndim == 1:
        R = np.diag(R)
    if Qd.shape != (n, n) or R.shape != (p, p):
        raise InputError(f"`steady_state_kalman` needs Qd of shape {(n, n)} and R of shape "
                         f"{(p, p)}, got {Qd.shape} and {R.shape}.")
    if not np.all(np.linalg.eigvalsh(0.5 * (R + R.T)) > 0):
        raise InputError("`steady_state_kalman(measurement_covariance=...)` must be positive "
                         "definite: every sensor needs a noise std > 0.")
    try:
        P = scipy.linalg.solve_discrete_are(Phi.T, C.T, 0.5 * (Qd + Qd.T), R)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise InputError(f"`steady_state_kalman`: the Riccati equation has no stabilizing "
                         f"solution ({err}). Check that the sensors observe every mode that "
                         "does not decay (`observability`).") from None
    P = 0.5 * (P + P.T)
    S = C @ P @ C.T + R
    L = np.linalg.solve(S, C @ P).T  # P Cᵀ S⁻¹ (S symmetric)
    # SciPy returns a "solution" for some undetectable pairs too (a random walk no sensor
    # sees: its gain ~1e-8, its error pole 1 - 1e-16): the error must decay.
    rho = float(np.abs(np.linalg.eigvals((np.eye(n) - L @ C) @ Phi)).max())
    if not np.isfinite(rho) or rho >= 1.0 - _MARGINAL:
        raise InputError(f"`steady_state_kalman`: the Riccati equation has no stabilizing "
                         f"solution (an error pole at |z| = {rho:.16g}): the sensors leave a "
                         "mode that does not decay unobserved (`observability`).")
    Pf = (np.eye(n) - L @ C) @ P
    return KalmanGain(L, P, 0.5 * (Pf + Pf.T))


# An error pole this close to the unit circle does not decay: a mode no sensor sees.
_MARGINAL = 1e-12


def discrete_process_covariance(A, process_noise, dt: float) -> np.ndarray:
    """`Qd = ∫0^dt e^{A s} Qc e^{Aᵀ s} ds` with `Qc = diag(q²)` (Van Loan).

    **Arguments:**

    - `A`: the continuous state matrix (1/s), shape (states, states).
    - `process_noise`: `q`, per state diffusion std (°C/√s), shape (states,), or the
      full diffusion covariance `Qc` (°C²/s), shape (states, states).
    - `dt`: sample period (s).

    **Returns:** `Qd` (°C²), shape (states, states), as NumPy.
    """
    import jax.numpy as jnp

    from ..dynamics._discretize import discretize_process_noise

    A = np.asarray(A, float)
    q = np.asarray(process_noise, float)
    Qc = np.diag(q ** 2) if q.ndim == 1 else q
    if Qc.shape != A.shape:
        raise InputError(f"`discrete_process_covariance(process_noise=...)` needs {A.shape[0]} "
                         f"values (one per state), got shape {q.shape}.")
    _, Qd = discretize_process_noise(jnp.asarray(A), jnp.asarray(Qc), float(dt))
    Qd = np.asarray(Qd, float)
    return 0.5 * (Qd + Qd.T)
