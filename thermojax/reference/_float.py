"""The float observer (float64 or float32), with a fixed operation order that C can repeat."""

from __future__ import annotations

import numpy as np

from ._faults import (ChannelMonitor, FaultConfig, hold_inputs, initial_inputs,
                      state_in_range)
from ._run import ObserverRun, play
from ._system import ObserverSystem


def ordered_matvec(columns, v, acc):
    """`acc + sum_j columns[j] * v[j]`, accumulated in order `j = 0, 1, ...`, each product
    and sum rounded to the array's dtype (what C does with `-ffp-contract=off`)."""
    for j in range(len(columns)):
        acc = acc + columns[j] * v[j]
    return acc


class SparseSum:
    """Row sums `s_i = M[i, j0] v[j0] + M[i, j1] v[j1] + ...` over the *nonzero* entries of
    row `i` only, in column order, left to right, each product and sum rounded to the
    dtype: the first nonzero term starts the sum (no `0 +`), exact zeros are skipped
    (so a NaN or infinity meets no zero coefficient). This is, operation for operation,
    the straight-line C that `generate_c` writes (`s = c0 * v0 + c1 * v1 + ...`).
    A row without nonzero entries is empty (`has_terms[i]` is False; its sum is `+0`).
    """

    def __init__(self, M, dtype):
        M = np.asarray(M, dtype=dtype)
        self.M, self.dtype = M, np.dtype(dtype)
        nz = M != 0
        before = np.cumsum(nz, axis=1) - nz              # nonzero entries left of (i, j)
        self.has_terms = nz.any(axis=1)
        self.plan = []
        for j in range(M.shape[1]):
            first = np.flatnonzero(nz[:, j] & (before[:, j] == 0))
            rest = np.flatnonzero(nz[:, j] & (before[:, j] > 0))
            if first.size or rest.size:
                self.plan.append((j, first, M[first, j], rest, M[rest, j]))

    def __call__(self, v) -> np.ndarray:
        acc = np.zeros(self.M.shape[0], self.dtype)
        for j, first, c_first, rest, c_rest in self.plan:
            if first.size:
                acc[first] = c_first * v[j]
            if rest.size:
                acc[rest] = acc[rest] + c_rest * v[j]
        return acc


class FloatObserver:
    """The observer of `ObserverSystem` in IEEE float64 or float32, with channel supervision.

    Untrusted inputs: each input sample outside `FaultConfig.input_limits` (exclusive;
    NaN and ±inf always) is replaced by that input's last good value (`hold_inputs`),
    compared in the observer's dtype, before anything else; `self.input_fault` is the
    step's mask. After the step `self.state_ok` says whether every state is strictly
    inside `FaultConfig.limits` (False for NaN); `run` then reports no channel healthy.

    Operation order (fixed, and the same in the generated straight-line C; see
    `SparseSum`): each row is one left-to-right sum over the row's nonzero coefficients
    only, the first product starting the sum. Prediction: row `i` of `[Phi B0 B1]` times
    `[x[k-1]; u[k-1]; u[k]]` (a row without nonzero entries predicts `+0`). Predicted
    output: row `i` of `[C D]` times `[x⁻; u[k]]`, and `r = y - that` (`r = y` for an empty
    row). Correction: row `i` of the gain of the channels in use (its other columns are
    zero) times `r`, then `x⁻_i + that` (rows without a nonzero gain are left as they
    are). Exact zeros are never multiplied. No fused multiply-add.

    **Arguments:**

    - `system`: an `ObserverSystem`.
    - `faults`: a `FaultConfig` (default: plausibility −55…+125 °C only).
    - `dtype`: `numpy.float64` or `numpy.float32`; matrices are rounded to it once.
    - `biases`: an optional `BiasEvaluator`: after each step, `self.bias (q,)` holds the
      bias channels evaluated (in float64) from the corrected estimate and `u[k]`, and
      `run` records them (`ObserverRun.bias`).
    """

    def __init__(self, system: ObserverSystem, faults: FaultConfig | None = None,
                 dtype=np.float64, biases=None):
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"`FloatObserver(dtype={dtype})`: expected float64 or float32.")
        self.system, self.dtype = system, dtype
        self.biases = biases
        self.bias = None
        self.faults = FaultConfig() if faults is None else faults
        p = system.n_outputs
        self._predict = SparseSum(np.hstack([system.Phi, system.B0, system.B1]), dtype)
        self._output = SparseSum(np.hstack([system.C, system.D]), dtype)
        self._gains = [SparseSum(L, dtype) for L in system.gain_table]
        self.limits = np.asarray(self.faults.limits, dtype=dtype)
        self.rails = self.faults.rails_array(p).astype(dtype)
        self.threshold = self.faults.threshold_array(p).astype(dtype)
        self.input_limits = self.faults.input_limits_array(system).astype(dtype)
        self.state_limits = np.tile(self.limits, (system.n_states, 1))
        self.u_start = initial_inputs(self.faults.input_limits_array(system)).astype(dtype)
        self.monitor = ChannelMonitor(p, self.faults.wire_break_after, self.faults.recover_after,
                                      self.faults.gate)
        self.x = np.zeros(system.n_states, dtype)
        self.u_prev = self.u_start.copy()
        self.started = False
        self.input_fault, self.state_ok, self.saturations = 0, True, 0

    def reset(self, x0) -> None:
        """Start over from `x0 (n,)`; the next step corrects `x⁻[0] = x0` (no prediction)."""
        self.x = np.array(x0, dtype=self.dtype).reshape(self.system.n_states)
        self.started = False
        self.u_prev = self.u_start.copy()       # held before the first good sample
        self.input_fault, self.saturations = 0, 0
        self.state_ok = state_in_range(self.x, self.state_limits)
        self.monitor.reset()
        if self.biases is not None:
            self.biases.reset()

    def step(self, u, y, open_circuit=None):
        """One observer step with inputs `u (m,)`, measurements `y (p,)` and the front
        end's open-circuit flags; returns `(x, r, in_use_mask)`."""
        dt = self.dtype
        with np.errstate(over="ignore"):  # too large for float32: ±inf (held, not plausible)
            u, y = np.asarray(u, dtype=dt), np.asarray(y, dtype=dt)
        u, self.input_fault = hold_inputs(u, self.u_prev, self.input_limits)
        p, n = self.system.n_outputs, self.system.n_states
        if self.started:
            xm = self._predict(np.concatenate([self.x, self.u_prev, u]))
        else:
            xm = self.x.copy()
        pred = self._output(np.concatenate([xm, u]))
        r = np.where(self._output.has_terms, y - pred, y)
        oc = np.zeros(p, bool) if open_circuit is None else np.asarray(open_circuit, bool)
        plausible = [bool(not oc[j] and self.limits[0] < y[j] < self.limits[1])
                     for j in range(p)]
        railed = [plausible[j] and bool(y[j] <= self.rails[j, 0] or y[j] >= self.rails[j, 1])
                  for j in range(p)]
        large = [plausible[j] and bool(abs(r[j]) > self.threshold[j]) for j in range(p)]
        mask = self.monitor.update(plausible, railed, large, self.started)
        if mask:
            gain = self._gains[mask]
            corr = gain(r)
            xm = np.where(gain.has_terms, xm + corr, xm)
        self.x, self.u_prev, self.started = xm, u, True
        self.state_ok = state_in_range(xm, self.state_limits)
        if self.biases is not None:
            self.bias = self.biases.step(xm, u)
        return xm, r, mask

    def run(self, x0, u, y, open_circuit=None) -> ObserverRun:
        """Play back `u (T, m)` and `y (T, p)` from `x0`; `open_circuit (T, p)` flags."""
        return play(self, "FloatObserver", x0, u, y, open_circuit, self.dtype)
