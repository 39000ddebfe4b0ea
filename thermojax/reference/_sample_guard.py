"""Bad samples held and flagged in the filter-form observers (gain-scheduled, trimmed),
as the fixed-gain ones do (docs/observer.md §5), in plain Python and, the same
comparisons, in C (`_filter_form.guard_c`):

- an input outside its limits (exclusive; NaN and ±inf always) is replaced by its last
  good value (`hold_inputs`; before the first, the middle of its limits), bit j of
  `input_fault` set;
- a reading outside the plausibility limits (exclusive; NaN and ±inf always) gives no
  correction and does not schedule, bit j of `reading_fault` set.

One NaN input no longer turns every later estimate into NaN, and a 1e6 °C reading is
not trusted.
"""

from __future__ import annotations

import math
import types

import numpy as np

from ._faults import FaultConfig, default_input_limits, initial_inputs

READING_LIMITS = FaultConfig.limits  # °C, the fixed-gain observers' default


def design_input_limits(Phi, B0, B1, C, D, reading_limits=READING_LIMITS) -> np.ndarray:
    """`(m, 2)` default input limits of a design's matrices (`default_input_limits`)."""
    system = types.SimpleNamespace(Phi=np.asarray(Phi, float), B0=np.asarray(B0, float),
                                   B1=np.asarray(B1, float), C=np.asarray(C, float),
                                   D=np.asarray(D, float), n_states=np.shape(Phi)[0],
                                   n_inputs=np.shape(B0)[1])
    return default_input_limits(system, reading_limits)


class SampleGuard:
    """Input holding and reading plausibility of one run (see the module)."""

    def __init__(self, input_limits, reading_limits=READING_LIMITS):
        lim = np.asarray(input_limits, float).reshape(-1, 2)
        self.u_lo = [float(v) for v in lim[:, 0]]
        self.u_hi = [float(v) for v in lim[:, 1]]
        self.u_start = [float(v) for v in initial_inputs(lim)]
        self.y_lo, self.y_hi = float(reading_limits[0]), float(reading_limits[1])
        if not self.y_lo < self.y_hi:
            raise ValueError(f"`SampleGuard`: reading limits {reading_limits} need low < high.")
        self.reset()

    def reset(self) -> None:
        self.u_held = list(self.u_start)

    def inputs(self, u: list) -> tuple[list, int]:
        """`(u used, fault mask)`: each input inside its limits, else its last good value."""
        mask = 0
        for j, v in enumerate(u):
            if self.u_lo[j] < v < self.u_hi[j]:
                self.u_held[j] = v
            else:
                mask |= 1 << j
        return list(self.u_held), mask

    def readings(self, y: list) -> tuple[list, int]:
        """`(readings with the implausible ones NaN, fault mask)`."""
        out, mask = [], 0
        for j, v in enumerate(y):
            if self.y_lo < v < self.y_hi:
                out.append(v)
            else:
                out.append(math.nan)
                mask |= 1 << j
        return out, mask
