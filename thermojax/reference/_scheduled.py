"""The gain-scheduled observer for firmware: matrices and gains designed at several
operating points, interpolated at run time by a measured temperature, in float64,
operation for operation as the generated C (`_scheduled_c.py`).

A nonlinear network (temperature-dependent conductances, radiation) linearized at one
temperature is right near it only. `thermojax.observer.scheduled_design` linearizes it
at `K` uniform temperatures `T_0 < … < T_K−1` and designs the filter-form observer at
each (`Phi_i`, `B0_i`, `B1_i`, the steady-state Kalman gain `L_i`; `C`, `D` shared).
Each step:

    s   = y[k][by] if finite, else the last s;   clamped to T_0 … T_K−1
    j   = the last i ≤ K − 2 with T_i ≤ s;   w = (s − T_j) / (T_j+1 − T_j)
    M   = M_j + w (M_j+1 − M_j)          elementwise, for Phi, B0, B1, L
    x⁻  = Phi x + B0 u[k−1] + B1 u[k]    (not at the first step: x⁻ = x0)
    x   = x⁻ + L (y − C x⁻ − D u[k])

Every sum in index order, every product as written (a Python float is a C double;
`-ffp-contract=off`). Bad samples are held and flagged (`_sample_guard`): an input outside
its limits is held at its last good value, a reading outside the plausibility limits (NaN
included) contributes no correction and does not schedule; otherwise every sensor is used
at every step: the channel state machine of the fixed-gain observer (docs/observer.md §5)
is not part of the scheduled one.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._filter_form import filter_step
from ._sample_guard import READING_LIMITS, SampleGuard, design_input_limits


@dataclasses.dataclass(frozen=True, eq=False)
class ScheduledDesign:
    """`points (K,)` °C, `Phi (K, n, n)`, `B0`, `B1 (K, n, m)`, `L (K, n, p)`, `C (p, n)`,
    `D (p, m)`, `by` (the index of the scheduling sensor among the outputs)."""

    points: np.ndarray
    Phi: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    L: np.ndarray
    C: np.ndarray
    D: np.ndarray
    by: int

    def __post_init__(self):
        K = len(self.points)
        if K < 2 or np.any(np.diff(self.points) <= 0):
            raise ValueError(f"`ScheduledDesign`: need two or more increasing points, got "
                             f"{list(self.points)}.")
        for name in ("Phi", "B0", "B1", "L"):
            if getattr(self, name).shape[0] != K:
                raise ValueError(f"`ScheduledDesign`: {name} has "
                                 f"{getattr(self, name).shape[0]} points, not {K}.")


@dataclasses.dataclass(frozen=True, eq=False)
class ScheduledRun:
    """`states (T, n)` °C after each correction and the scheduling value `s (T,)` used;
    `input_fault`, `reading_fault (T,)`: the bit masks of inputs held and readings not
    trusted at each step (`_sample_guard`; None from the C harness, which writes states)."""

    states: np.ndarray
    s: np.ndarray
    input_fault: np.ndarray | None = None
    reading_fault: np.ndarray | None = None


class ScheduledObserver:
    """The scheduled observer in plain float64 Python (see the module)."""

    def __init__(self, design: ScheduledDesign, input_limits=None,
                 reading_limits=READING_LIMITS):
        d = design
        self.d = d
        if input_limits is None:
            input_limits = design_input_limits(d.Phi[0], d.B0[0], d.B1[0], d.C, d.D,
                                               reading_limits)
        self.guard = SampleGuard(input_limits, reading_limits)
        self.points = [float(v) for v in d.points]
        self.tables = {k: np.asarray(getattr(d, k), float).tolist()
                       for k in ("Phi", "B0", "B1", "L")}
        self.C, self.D = np.asarray(d.C, float).tolist(), np.asarray(d.D, float).tolist()

    def _interpolated(self, s):
        pts = self.points
        K = len(pts)
        s = pts[0] if s < pts[0] else pts[K - 1] if s > pts[K - 1] else s
        j = 0
        while j < K - 2 and pts[j + 1] <= s:
            j += 1
        w = (s - pts[j]) / (pts[j + 1] - pts[j])
        out = {}
        for k, tab in self.tables.items():
            a, b = tab[j], tab[j + 1]
            out[k] = [[a[r][c] + w * (b[r][c] - a[r][c]) for c in range(len(a[r]))]
                      for r in range(len(a))]
        return out, s

    def run(self, x0, u, y) -> ScheduledRun:
        """Play back `u (T, m)`, `y (T, p)` from `x0 (n,)`."""
        u, y = np.asarray(u, float).tolist(), np.asarray(y, float).tolist()
        x = [float(v) for v in x0]
        s_last = self.points[0]
        states, used = np.empty((len(u), len(x))), np.empty(len(u))
        u_fault, y_fault = np.zeros(len(u), np.int64), np.zeros(len(u), np.int64)
        self.guard.reset()
        u_prev = None
        for k in range(len(u)):
            u_k, u_fault[k] = self.guard.inputs(u[k])
            y_k, y_fault[k] = self.guard.readings(y[k])
            s = y_k[self.d.by]
            s = s if math.isfinite(s) else s_last
            M, s = self._interpolated(s)
            s_last = s
            x = filter_step(M, self.C, self.D, x, u_prev, u_k, y_k)
            u_prev = u_k
            states[k], used[k] = x, s
        return ScheduledRun(states, used, u_fault, y_fault)
