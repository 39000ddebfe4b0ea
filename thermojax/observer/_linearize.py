"""A nonlinear network linearized at a uniform operating temperature with no power.

The exported observer (`_export`, `--operating-point`) and the gain-scheduled one
(`_schedule`, one linearization per point) both design on it (docs/observer.md §2, §12).
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError


def linearize(model, system, power_inputs, T_op: float, where: str):
    """`(A, B)` of the model linearized at uniform `T_op` °C, zero power."""
    import jax
    import jax.numpy as jnp

    n, m = system.A.shape[0], system.B.shape[1]
    x_op = jnp.full(n, T_op)
    u_op = jnp.asarray([0.0 if j in power_inputs else T_op for j in range(m)])
    rate = lambda x, u: model.nonlinear_rate(system, x, u)
    f = np.asarray(system.A @ x_op + system.B @ u_op + rate(x_op, u_op))
    if np.abs(f).max() > 1e-9 * (1 + abs(T_op)):
        raise InputError(f"the nonlinear model is not at rest at a uniform {T_op} °C with no "
                         f"power (dT/dt up to {np.abs(f).max():.3g} K/s); the export "
                         "linearizes at such an equilibrium only.", file=where,
                         field="--operating-point")
    Nx, Nu = jax.jacfwd(rate, argnums=(0, 1))(x_op, u_op)
    return system.A + Nx, system.B + Nu, np.asarray(x_op), np.asarray(u_op)
