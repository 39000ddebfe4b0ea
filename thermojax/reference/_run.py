"""What a playback returns, for every observer of the reference."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class ObserverRun:
    """A playback's record, one row per observer step.

    - `states (T, n)`: corrected estimates `x[k]` (physical units for float observers,
      integer codes for fixed-point ones; `FixedObserver.decode_states` converts).
    - `residuals (T, p)`: prediction residuals `y - C x⁻ - D u` (same units).
    - `in_use (T,)`: bit mask of the channels used in the correction.
    - `healthy (T,)`, `wire_break (T,)`: bit masks of the channel flags after the step;
      `healthy` is 0 in a step whose state is not in range (`state_ok`).
    - `bias (T, q)`: the bias channels evaluated from the estimates (float observers
      with a `BiasEvaluator`), else None.
    - `input_fault (T,)`: bit mask of the inputs that were not plausible (NaN, infinite or
      outside `FaultConfig.input_limits`) and replaced by their last good value.
    - `state_ok (T,)`: 1 when every corrected state is finite, strictly inside the
      plausibility limits and (fixed point) nothing saturated in the step, else 0.
    - `saturations (T,)`: steps so far in which a fixed-point state saturated (the
      prediction or the correction clamped to the word), saturating at 65535; 0 in float.
    """

    states: np.ndarray
    residuals: np.ndarray
    in_use: np.ndarray
    healthy: np.ndarray
    wire_break: np.ndarray
    bias: np.ndarray | None = None
    input_fault: np.ndarray | None = None
    state_ok: np.ndarray | None = None
    saturations: np.ndarray | None = None


def check_playback(name: str, u, y, open_circuit, m: int, p: int, dtype):
    with np.errstate(over="ignore"):      # too large for float32: ±inf, then held
        u = np.asarray(u, dtype=dtype)
        y = np.asarray(y, dtype=dtype)
    if u.ndim != 2 or u.shape[1] != m or y.ndim != 2 or y.shape != (u.shape[0], p):
        raise ValueError(f"`{name}.run` got inputs {u.shape} and measurements {y.shape}; "
                         f"expected (T, {m}) and (T, {p}).")
    if open_circuit is None:
        oc = np.zeros((u.shape[0], p), dtype=bool)
    else:
        oc = np.asarray(open_circuit, dtype=bool)
        if oc.shape != y.shape:
            raise ValueError(f"`{name}.run(open_circuit=...)` has shape {oc.shape}; expected "
                             f"{y.shape} (one flag per measurement).")
    return u, y, oc


def play(observer, name: str, x0, u, y, open_circuit, dtype) -> ObserverRun:
    """Reset `observer` to `x0` and step it through `u (T, m)` and `y (T, p)` (in its own
    units and `dtype`), recording states, residuals and channel flags."""
    s = observer.system
    u, y, oc = check_playback(name, u, y, open_circuit, s.n_inputs, s.n_outputs, dtype)
    T = u.shape[0]
    X = np.empty((T, s.n_states), dtype)
    R = np.empty((T, s.n_outputs), dtype)
    flags = np.empty((4, T), np.uint8)
    input_fault = np.empty(T, np.uint32)
    saturations = np.empty(T, np.uint16)
    evaluator = getattr(observer, "biases", None)
    bias = None if evaluator is None else np.empty((T, evaluator.n_channels))
    observer.reset(x0)
    for k in range(T):
        X[k], R[k], flags[0, k] = observer.step(u[k], y[k], oc[k])
        flags[1, k], flags[2, k] = observer.monitor.flags()
        flags[3, k] = observer.state_ok
        if not observer.state_ok:
            flags[1, k] = 0
        input_fault[k], saturations[k] = observer.input_fault, observer.saturations
        if bias is not None:
            bias[k] = observer.bias
    return ObserverRun(X, R, flags[0], flags[1], flags[2], bias, input_fault, flags[3],
                       saturations)
