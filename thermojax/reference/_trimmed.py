"""The end-of-line trimmed observer for firmware: matrices and gains designed over a grid
of per-unit scale factors, interpolated once at initialisation from the unit's factor
table, in float64, operation for operation as the generated C (`_trimmed_c.py`).

`thermojax.observer.trim_design` designs the filter-form observer at every point of the
grid `g_0 × … × g_D−1` (`Phi_g`, `B0_g`, `B1_g`, the steady-state Kalman gain `L_g`,
stored in C order, the last factor fastest; `C`, `D` shared). At initialisation, from the
unit's factors `f (D,)`:

    f_d = 1 if not finite (erased flash: the nominal unit)    counted in `replaced`
    f_d clamped to g_d[0] … g_d[K_d−1]
    j_d = the last i ≤ K_d − 2 with g_d[i] ≤ f_d;   w_d = (f_d − g_d[j_d]) / (g_d[j_d+1] − g_d[j_d])
    M   = Σ over corners b = 0 … 2^D − 1 (bit d of b: upper neighbour along d) of
          (Π_d (w_d if bit else 1 − w_d)) · M[Σ_d (j_d + bit) stride_d]

the product and the index built d = 0, 1, …, the sum from 0.0 over b in order, for Phi,
B0, B1 and L. Every step is then `filter_step` with those matrices.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._filter_form import filter_step
from ._sample_guard import READING_LIMITS, SampleGuard, design_input_limits

MATRICES = ("Phi", "B0", "B1", "L")


@dataclasses.dataclass(frozen=True, eq=False)
class TrimDesign:
    """`names (D,)` of the factors, `grids` (D arrays, each increasing), `Phi (G, n, n)`,
    `B0`, `B1 (G, n, m)`, `L (G, n, p)` at the `G = Π K_d` grid points in C order,
    `C (p, n)`, `D (p, m)`."""

    names: tuple[str, ...]
    grids: tuple[np.ndarray, ...]
    Phi: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    L: np.ndarray
    C: np.ndarray
    D: np.ndarray

    def __post_init__(self):
        if len(self.names) != len(self.grids) or not self.grids:
            raise ValueError(f"`TrimDesign`: {len(self.names)} names for {len(self.grids)} "
                             "grids (one or more of each).")
        for name, g in zip(self.names, self.grids):
            if len(g) < 2 or np.any(np.diff(g) <= 0):
                raise ValueError(f"`TrimDesign`: the grid of {name!r} needs two or more "
                                 f"increasing values, got {list(g)}.")
        G = int(np.prod([len(g) for g in self.grids]))
        for name in MATRICES:
            if getattr(self, name).shape[0] != G:
                raise ValueError(f"`TrimDesign`: {name} has {getattr(self, name).shape[0]} "
                                 f"grid points, not {G}.")

    @property
    def strides(self) -> list[int]:
        """The step in the stacked tables of one grid step along each factor."""
        out, s = [], 1
        for g in reversed(self.grids):
            out.insert(0, s)
            s *= len(g)
        return out


@dataclasses.dataclass(frozen=True)
class Trim:
    """A unit's matrices (`Phi`, `B0`, `B1`, `L` as nested lists), the factors used (after
    clamping) and how many factors were not finite (taken as 1)."""

    matrices: dict
    factors: tuple[float, ...]
    replaced: int


def trim_matrices(design: TrimDesign, factors) -> Trim:
    """The unit's matrices interpolated at `factors (D,)` (see the module)."""
    grids = [[float(v) for v in g] for g in design.grids]
    f = [float(v) for v in factors]
    if len(f) != len(grids):
        raise ValueError(f"`trim_matrices`: {len(f)} factors for the design's {len(grids)} "
                         f"({', '.join(design.names)}).")
    js, ws, used, replaced = [], [], [], 0
    for g, v in zip(grids, f):
        if not math.isfinite(v):
            v, replaced = 1.0, replaced + 1
        K = len(g)
        v = g[0] if v < g[0] else g[K - 1] if v > g[K - 1] else v
        j = 0
        while j < K - 2 and g[j + 1] <= v:
            j += 1
        js.append(j)
        ws.append((v - g[j]) / (g[j + 1] - g[j]))
        used.append(v)
    strides = design.strides
    out = {}
    for name in MATRICES:
        tab = np.asarray(getattr(design, name), float)
        rows, cols = tab.shape[1], tab.shape[2]
        tab = tab.tolist()
        acc = [[0.0] * cols for _ in range(rows)]
        for b in range(1 << len(grids)):
            wt, idx = 1.0, 0
            for d in range(len(grids)):
                bit = (b >> d) & 1
                wt = wt * (ws[d] if bit else 1.0 - ws[d])
                idx = idx + (js[d] + bit) * strides[d]
            for r in range(rows):
                for c in range(cols):
                    acc[r][c] = acc[r][c] + wt * tab[idx][r][c]
        out[name] = acc
    return Trim(out, tuple(used), replaced)


def trimmed_input_limits(design: TrimDesign, reading_limits=READING_LIMITS):
    """`(m, 2)` default input limits of a trimmed design: those of its first grid design
    (the same for every unit, so the C, whose factors come at run time, agrees)."""
    return design_input_limits(design.Phi[0], design.B0[0], design.B1[0], design.C,
                               design.D, reading_limits)


class TrimmedObserver:
    """The trimmed observer in plain float64 Python (see the module)."""

    def __init__(self, design: TrimDesign, factors, input_limits=None,
                 reading_limits=READING_LIMITS):
        self.d = design
        self.trim = trim_matrices(design, factors)
        self.C, self.D = np.asarray(design.C, float).tolist(), np.asarray(design.D, float).tolist()
        if input_limits is None:
            input_limits = trimmed_input_limits(design, reading_limits)
        self.guard = SampleGuard(input_limits, reading_limits)
        self.input_fault = self.reading_fault = None

    def run(self, x0, u, y) -> np.ndarray:
        """Play back `u (T, m)`, `y (T, p)` from `x0 (n,)`: the estimates `(T, n)` °C. Bad
        samples are held and flagged (`_sample_guard`): the bit masks of each step are
        `input_fault` and `reading_fault` (T,) after the run."""
        u, y = np.asarray(u, float).tolist(), np.asarray(y, float).tolist()
        x = [float(v) for v in x0]
        states = np.empty((len(u), len(x)))
        u_fault, y_fault = np.zeros(len(u), np.int64), np.zeros(len(u), np.int64)
        self.guard.reset()
        u_prev = None
        for k in range(len(u)):
            u_k, u_fault[k] = self.guard.inputs(u[k])
            y_k, y_fault[k] = self.guard.readings(y[k])
            x = filter_step(self.trim.matrices, self.C, self.D, x, u_prev, u_k, y_k)
            u_prev = u_k
            states[k] = x
        self.input_fault, self.reading_fault = u_fault, y_fault
        return states
