"""The discrete observer in JAX: filter form, jit-able, vmap-able, differentiable.

The plant is the sampled system of `DiscreteSystem` (first-order hold for `"foh"`
inputs, zero-order for `"zoh"`, both exact):

    x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1],      y[k] = C x[k] + D u[k].

The observer is the **filter form** ("current estimator"): the estimate at sample `k`
already uses the reading `y[k]`. With a prior `x̂⁻[0] = x0` and for `k = 0, 1, ..., N−1`:

    predict   x̂⁻[k] = Phi x̂[k−1] + B0 u[k−1] + B1 u[k]        (k ≥ 1; x̂⁻[0] = x0)
    innovate  r[k]  = y[k] − C x̂⁻[k] − D u[k]
    correct   x̂[k]  = x̂⁻[k] + L r[k]

in that order, each a plain matrix-vector product in float64, no other operation (no
clipping, no covariance update: `L` is constant). Its error obeys
`x[k] − x̂[k] = (I − L C) Phi (x[k−1] − x̂[k−1])`, so the observer's poles are
`eig(Phi − L C Phi)` (`place_observer_gain`), and a steady-state Kalman gain
`L = P Cᵀ (C P Cᵀ + R)⁻¹` makes it the steady-state Kalman filter
(`steady_state_kalman`). A reference implementation must reproduce these three lines
in this order to reproduce `run_observer` to roundoff (1e-9 over long playbacks).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..model._system import DiscreteSystem


class Observer(eqx.Module):
    """A constant-gain discrete observer in filter form (see the module docstring).

    - `system`: the `DiscreteSystem` at the observer rate (`Phi`, `B0`, `B1`, `C`, `D`,
      `dt`).
    - `gain`: `L`, shape (states, outputs), from `place_observer_gain` or
      `steady_state_kalman`.
    """

    system: DiscreteSystem
    gain: Float[Array, "states outputs"]

    def __check_init__(self):
        n, p = self.system.Phi.shape[0], self.system.C.shape[0]
        if self.gain.shape != (n, p):
            raise ValueError(f"`Observer(gain=...)` needs shape {(n, p)} (states, outputs), "
                             f"got {self.gain.shape}.")

    @property
    def error_dynamics(self) -> Float[Array, "states states"]:
        """`(I − L C) Phi`: the map of the filtered estimation error over one step."""
        s = self.system
        return s.Phi - self.gain @ (s.C @ s.Phi)

    def predict(self, x: Float[Array, " states"], u_prev: Float[Array, " inputs"],
                u: Float[Array, " inputs"]) -> Float[Array, " states"]:
        """`x̂⁻[k] = Phi x̂[k−1] + B0 u[k−1] + B1 u[k]` (°C)."""
        s = self.system
        return s.Phi @ x + s.B0 @ u_prev + s.B1 @ u

    def innovation(self, x_pred: Float[Array, " states"], u: Float[Array, " inputs"],
                   y: Float[Array, " outputs"]) -> Float[Array, " outputs"]:
        """`r[k] = y[k] − C x̂⁻[k] − D u[k]` (°C)."""
        s = self.system
        return y - s.C @ x_pred - s.D @ u

    def correct(self, x_pred: Float[Array, " states"], u: Float[Array, " inputs"],
                y: Float[Array, " outputs"]) -> Float[Array, " states"]:
        """`x̂[k] = x̂⁻[k] + L r[k]` (°C)."""
        return x_pred + self.gain @ self.innovation(x_pred, u, y)

    def step(self, x: Float[Array, " states"], u_prev: Float[Array, " inputs"],
             u: Float[Array, " inputs"], y: Float[Array, " outputs"]
             ) -> Float[Array, " states"]:
        """One sample: predict from `x̂[k−1]`, then correct with `y[k]`; returns `x̂[k]`."""
        return self.correct(self.predict(x, u_prev, u), u, y)


Observer.__init__.__doc__ = """**Arguments:**

- `system`: the `DiscreteSystem` at the observer rate.
- `gain`: the filter-form gain `L`, shape (states, outputs).
"""


class ObserverRun(eqx.Module):
    """What `run_observer` returns, per sample `k` (rows):

    - `states`: the filtered estimates `x̂[k]` (°C), shape (times, states).
    - `predicted`: the predictions `x̂⁻[k]` (°C), shape (times, states).
    - `innovations`: `r[k] = y[k] − C x̂⁻[k] − D u[k]` (°C), shape (times, outputs).
    """

    states: Float[Array, "times states"]
    predicted: Float[Array, "times states"]
    innovations: Float[Array, "times outputs"]


def run_observer(observer: Observer, inputs: Float[Array, "times inputs"],
                 outputs: Float[Array, "times outputs"], x0: Float[Array, " states"]
                 ) -> ObserverRun:
    """Run the observer over one run with `jax.lax.scan` (see the module docstring).

    Pure and traceable: `jax.jit` it, `jax.vmap` it over runs (inputs, outputs and
    `x0` batched, the observer shared), differentiate it with respect to the
    observer's leaves (the system's matrices, the gain), the data or `x0`.

    **Arguments:**

    - `observer`: an `Observer`.
    - `inputs`: `u[k]` at the observer's samples, shape (times, inputs), SI units
      (°C for temperatures, W for powers).
    - `outputs`: the readings `y[k]` (°C), shape (times, outputs).
    - `x0`: the prior estimate `x̂⁻[0]` (°C), shape (states,).

    **Returns:** an `ObserverRun`.
    """
    if inputs.shape[0] != outputs.shape[0]:
        raise ValueError(f"`run_observer` needs as many input samples as readings, got "
                         f"{inputs.shape[0]} and {outputs.shape[0]}.")
    if inputs.shape[0] == 0:
        raise ValueError("`run_observer` needs at least one sample.")
    r0 = observer.innovation(x0, inputs[0], outputs[0])
    x_first = x0 + observer.gain @ r0

    def body(carry, data):
        x, u_prev = carry
        u, y = data
        x_pred = observer.predict(x, u_prev, u)
        r = observer.innovation(x_pred, u, y)
        x_new = x_pred + observer.gain @ r
        return (x_new, u), (x_new, x_pred, r)

    _, (xs, preds, rs) = jax.lax.scan(body, (x_first, inputs[0]), (inputs[1:], outputs[1:]))
    return ObserverRun(jnp.concatenate([x_first[None, :], xs], axis=0),
                       jnp.concatenate([x0[None, :], preds], axis=0),
                       jnp.concatenate([r0[None, :], rs], axis=0))
