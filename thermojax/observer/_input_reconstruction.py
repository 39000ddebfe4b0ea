"""Lag compensation by input reconstruction: estimate an unmeasured input as a state.

A slow sensor (an RTD in its sheath) reads a lagged version of the fluid temperature
`u_j` that drives it. Augment the state with `u_j` itself, modelled as a random walk
(`du_j = dβ`, diffusion std `input_noise` in °C/√s), and run an observer on

    d/dt [x; u_j] = [[A, B_j], [0, 0]] [x; u_j] + [B_rest; 0] u_rest,
    y = [C, D_j] [x; u_j] + D_rest u_rest.

The estimate of `u_j` leads the raw reading: the observer inverts the sensor's lag as
far as the sensor noise allows. `input_noise` sets the trade-off: a larger value lets
`û_j` move faster (shorter 90 % time) and passes more sensor noise
(`estimate_noise_std`). Between samples the augmented model holds `u_j` constant.
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError
from ._kalman import discrete_process_covariance, steady_state_kalman
from ._observer import Observer


def augment_unknown_input(system, input: int):
    """The `LinearSystem` with input `input` moved into the state (as its last entry).

    **Arguments:**

    - `system`: a continuous `LinearSystem` with `n` states and `m` inputs.
    - `input`: the index of the unknown input.

    **Returns:** a `LinearSystem` with `n + 1` states (the last one `u_input`, °C or W)
    and `m − 1` inputs; `capacitance` is `None` (no longer a reciprocal network).
    """
    import jax.numpy as jnp

    from ..model._system import LinearSystem

    n, m = system.B.shape
    if not 0 <= input < m:
        raise InputError(f"`augment_unknown_input(input={input})` must index one of the "
                         f"system's {m} inputs (0-based).")
    rest = np.array([j for j in range(m) if j != input], dtype=int)
    A = jnp.concatenate([jnp.concatenate([system.A, system.B[:, input:input + 1]], axis=1),
                         jnp.zeros((1, n + 1), dtype=system.A.dtype)], axis=0)
    B = jnp.concatenate([system.B[:, rest], jnp.zeros((1, rest.size), dtype=system.A.dtype)],
                        axis=0)
    C = jnp.concatenate([system.C, system.D[:, input:input + 1]], axis=1)
    D = system.D[:, rest]
    holds = tuple(system.holds[j] for j in rest)
    return LinearSystem(A, B, C, D, holds=holds)


def reconstruction_observer(model, dt: float, input: str | int, input_noise: float,
                            process_noise=None, noise=None) -> Observer:
    """A steady-state Kalman observer that reconstructs an unmeasured input.

    **Arguments:**

    - `model`: a `ThermalModel` (its sensor `noise` and node `process_noise` are the
      defaults) or a `ThermalNetwork`.
    - `dt`: observer sample period (s).
    - `input`: the unknown input, by column name (e.g. `"T_fluid"`) or index.
    - `input_noise`: diffusion std of the input's random walk (°C/√s for a temperature):
      the speed/noise trade-off.
    - `process_noise`: per node diffusion std (°C/√s); default the model's, else 1e-3.
    - `noise`: per sensor noise std (°C); default the model's, else 0.01.

    **Returns:** an `Observer` over the augmented state `[x; u_input]` (last entry the
    reconstructed input), whose inputs are the remaining ones.
    """
    import jax.numpy as jnp

    from ..dynamics._discretize import discretize
    from ..model._model import DEFAULT_NOISE, DEFAULT_PROCESS_NOISE, ThermalModel
    from ..model._network import ThermalNetwork

    if isinstance(model, ThermalModel):
        network, system = model.network, model.linear_system()
        q_default, r_default = np.asarray(model.process_noise), np.asarray(model.noise)
    elif isinstance(model, ThermalNetwork):
        network, system = model, model.linear_system()
        q_default = np.full(network.topology.n_nodes, DEFAULT_PROCESS_NOISE)
        r_default = np.full(len(network.topology.sensor_nodes), DEFAULT_NOISE)
    else:
        raise TypeError("`reconstruction_observer(model=...)` needs a `ThermalModel` or "
                        f"`ThermalNetwork`, got {type(model).__name__}.")
    names = network.topology.input_names
    if isinstance(input, str):
        if input not in names:
            raise InputError(f"`reconstruction_observer(input={input!r})`: the model's inputs "
                             f"are {list(names)}.")
        input = names.index(input)
    if not input_noise > 0:
        raise InputError(f"`reconstruction_observer(input_noise={input_noise})` must be > 0 "
                         "(°C/√s): with zero the observer never moves the input estimate.")
    q = np.broadcast_to(np.asarray(q_default if process_noise is None else process_noise,
                                   float), (system.A.shape[0],))
    r = np.broadcast_to(np.asarray(r_default if noise is None else noise, float),
                        (system.C.shape[0],))
    aug = augment_unknown_input(system, int(input))
    discrete = discretize(aug, dt)
    Qd = discrete_process_covariance(aug.A, np.concatenate([q, [float(input_noise)]]), dt)
    gain = steady_state_kalman(discrete, Qd, r ** 2).gain
    return Observer(discrete, jnp.asarray(gain))
