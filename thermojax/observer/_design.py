"""Observer design from a model: sample it, pick the sensors, compute the gain."""

from __future__ import annotations

import numpy as np

from .._errors import InputError
from ._kalman import discrete_process_covariance, steady_state_kalman
from ._observer import Observer
from ._pole_placement import observer_poles, place_observer_gain

METHODS = ("kalman", "poles")


def design_observer(model, dt: float, sensors=None, method: str = "kalman",
                    speedup: float = 4.0, min_time_constant: float | None = None,
                    pole_method: str = "YT") -> Observer:
    """A constant-gain observer of a thermal model at sample period `dt`.

    The model is sampled exactly (`thermojax.discretize`, per input its hold), the
    rows of `C`/`D` are restricted to `sensors` (a fallback observer when a channel
    is dropped), and the gain is:

    - `method="kalman"` (default): the steady-state Kalman gain, with `Qd` from each
      node's `process_noise` (°C/√s, default 1e-3) by Van Loan and `R` from each
      sensor's `noise` (°C, default 0.01) (`steady_state_kalman`);
    - `method="poles"`: pole placement at `speedup` × the open-loop poles,
      fast modes kept (`observer_poles`, `place_observer_gain`).

    Sensor offsets (`sensor_offset` effects) are not in `D`: subtract
    `model.output_offset()` from the readings first.

    **Arguments:**

    - `model`: a `ThermalModel` (or a `ThermalNetwork`: default noises).
    - `dt`: observer sample period (s).
    - `sensors`: sensor column names or indices to use; default all.
    - `method`: `"kalman"` or `"poles"`.
    - `speedup`, `min_time_constant`, `pole_method`: for `method="poles"`.

    **Returns:** an `Observer` (its `system.C` has one row per chosen sensor).
    """
    import equinox as eqx
    import jax.numpy as jnp

    from ..dynamics._discretize import discretize
    from ..model._model import DEFAULT_NOISE, DEFAULT_PROCESS_NOISE, ThermalModel
    from ..model._network import ThermalNetwork

    if method not in METHODS:
        raise InputError(f"`design_observer(method={method!r})` must be one of {list(METHODS)}.")
    if not dt > 0:
        raise InputError(f"`design_observer(dt={dt})` must be a positive sample period (s).")
    if isinstance(model, ThermalNetwork):
        network, system = model, model.linear_system()
        t = network.topology
        noise = np.full(len(t.sensor_nodes), DEFAULT_NOISE)
        q = np.full(t.n_nodes, DEFAULT_PROCESS_NOISE)
    elif isinstance(model, ThermalModel):
        network, system = model.network, model.linear_system()
        noise, q = np.asarray(model.noise, float), np.asarray(model.process_noise, float)
    else:
        raise TypeError("`design_observer(model=...)` needs a `ThermalModel` or "
                        f"`ThermalNetwork`, got {type(model).__name__}.")
    t = network.topology
    rows = _sensor_rows(sensors, t.sensor_names)
    idx = jnp.asarray(np.array(rows, dtype=int))
    system = eqx.tree_at(lambda s: (s.C, s.D), system, (system.C[idx], system.D[idx]))
    discrete = discretize(system, dt)
    if method == "kalman":
        Qd = discrete_process_covariance(system.A, q, dt)
        gain = steady_state_kalman(discrete, Qd, noise[rows] ** 2).gain
    else:
        poles = observer_poles(system, dt, speedup, min_time_constant)
        gain = place_observer_gain(discrete, poles, method=pole_method,
                                   state_names=t.node_names)
    return Observer(discrete, jnp.asarray(gain))


def _sensor_rows(sensors, names) -> list[int]:
    if sensors is None:
        return list(range(len(names)))
    rows = []
    for s in sensors:
        if isinstance(s, str):
            if s not in names:
                raise InputError(f"`design_observer(sensors=...)` names sensor '{s}', but the "
                                 f"model's sensors are {list(names)}.")
            rows.append(names.index(s))
        else:
            if not 0 <= int(s) < len(names):
                raise InputError(f"`design_observer(sensors=...)` refers to sensor {s}, but the "
                                 f"model has {len(names)}. Indices are 0-based.")
            rows.append(int(s))
    if not rows or len(set(rows)) != len(rows):
        raise InputError(f"`design_observer(sensors=...)` needs distinct sensors, at least one; "
                         f"got {list(sensors)}.")
    return rows
