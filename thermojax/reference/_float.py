"""The float observer (float64 or float32), with a fixed operation order that C can repeat."""

from __future__ import annotations

import numpy as np

from ._faults import ChannelMonitor, FaultConfig
from ._run import ObserverRun, play
from ._system import ObserverSystem


def ordered_matvec(columns, v, acc):
    """`acc + sum_j columns[j] * v[j]`, accumulated in order `j = 0, 1, ...`, each product
    and sum rounded to the array's dtype (what C does with `-ffp-contract=off`)."""
    for j in range(len(columns)):
        acc = acc + columns[j] * v[j]
    return acc


class FloatObserver:
    """The observer of `ObserverSystem` in IEEE float64 or float32, with channel supervision.

    Operation order (fixed, and the same in the generated C): every matrix-vector product
    starts from `0` and adds `M[:, j] * v[j]` for `j = 0, 1, ...`; prediction sums
    `Phi x`, then `B0 u[k-1]`, then `B1 u[k]` into one accumulator; the predicted output
    sums `C x⁻` then `D u[k]`; the correction adds `L[:, j] r[j]` over the channels in use,
    in order, then adds that to `x⁻`. No fused multiply-add.

    **Arguments:**

    - `system`: an `ObserverSystem`.
    - `faults`: a `FaultConfig` (default: plausibility −55…+125 °C only).
    - `dtype`: `numpy.float64` or `numpy.float32`; matrices are rounded to it once.
    """

    def __init__(self, system: ObserverSystem, faults: FaultConfig | None = None,
                 dtype=np.float64):
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"`FloatObserver(dtype={dtype})`: expected float64 or float32.")
        self.system, self.dtype = system, dtype
        self.faults = FaultConfig() if faults is None else faults
        p = system.n_outputs
        cols = lambda M: [np.ascontiguousarray(M[:, j], dtype=dtype) for j in range(M.shape[1])]
        self._phi, self._b0, self._b1 = cols(system.Phi), cols(system.B0), cols(system.B1)
        self._c, self._d = cols(system.C), cols(system.D)
        self._gains = [cols(L) for L in system.gain_table]
        self.limits = np.asarray(self.faults.limits, dtype=dtype)
        self.rails = self.faults.rails_array(p).astype(dtype)
        self.threshold = self.faults.threshold_array(p).astype(dtype)
        self.monitor = ChannelMonitor(p, self.faults.wire_break_after, self.faults.recover_after)
        self.x = np.zeros(system.n_states, dtype)
        self.u_prev = np.zeros(system.n_inputs, dtype)
        self.started = False

    def reset(self, x0) -> None:
        """Start over from `x0 (n,)`; the next step corrects `x⁻[0] = x0` (no prediction)."""
        self.x = np.array(x0, dtype=self.dtype).reshape(self.system.n_states)
        self.started = False
        self.monitor.reset()

    def step(self, u, y, open_circuit=None):
        """One observer step with inputs `u (m,)`, measurements `y (p,)` and the front
        end's open-circuit flags; returns `(x, r, in_use_mask)`."""
        dt = self.dtype
        u = np.asarray(u, dtype=dt)
        y = np.asarray(y, dtype=dt)
        p, n = self.system.n_outputs, self.system.n_states
        zero = np.zeros(n, dt)
        if self.started:
            acc = ordered_matvec(self._phi, self.x, zero)
            acc = ordered_matvec(self._b0, self.u_prev, acc)
            xm = ordered_matvec(self._b1, u, acc)
        else:
            xm = self.x
        pred = ordered_matvec(self._d, u, ordered_matvec(self._c, xm, np.zeros(p, dt)))
        r = y - pred
        oc = np.zeros(p, bool) if open_circuit is None else np.asarray(open_circuit, bool)
        plausible = [bool(not oc[j] and self.limits[0] <= y[j] <= self.limits[1])
                     for j in range(p)]
        railed = [plausible[j] and bool(y[j] <= self.rails[j, 0] or y[j] >= self.rails[j, 1])
                  for j in range(p)]
        large = [plausible[j] and bool(abs(r[j]) > self.threshold[j]) for j in range(p)]
        mask = self.monitor.update(plausible, railed, large)
        if mask:
            cols = self._gains[mask]
            acc = zero
            for j in range(p):
                if mask >> j & 1:
                    acc = acc + cols[j] * r[j]
            xm = xm + acc
        self.x, self.u_prev, self.started = xm, u, True
        return xm, r, mask

    def run(self, x0, u, y, open_circuit=None) -> ObserverRun:
        """Play back `u (T, m)` and `y (T, p)` from `x0`; `open_circuit (T, p)` flags."""
        return play(self, "FloatObserver", x0, u, y, open_circuit, self.dtype)
