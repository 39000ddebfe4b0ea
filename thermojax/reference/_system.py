"""The observer's matrices and its gain table, checked once, in float64."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np


def _subset_mask(key, p: int) -> int:
    idx = sorted({int(i) for i in key})
    if any(i < 0 or i >= p for i in idx):
        raise ValueError(f"`ObserverSystem(gains=...)`: subset {tuple(key)} names a sensor "
                         f"outside 0..{p - 1}. Sensor indices are 0-based rows of `C`.")
    return sum(1 << i for i in idx)


def _expand_gain(L, subset: list[int], n: int, p: int) -> np.ndarray:
    L = np.asarray(L, dtype=np.float64)
    if L.ndim == 1 and len(subset) == 1:
        L = L[:, None]
    full = np.zeros((n, p))
    if L.shape == (n, len(subset)):
        full[:, subset] = L
    elif L.shape == (n, p):
        others = [j for j in range(p) if j not in subset]
        if np.any(L[:, others] != 0):
            raise ValueError(f"`ObserverSystem(gains=...)`: the gain for sensors {tuple(subset)} "
                             f"has nonzero columns {others} for sensors outside the subset. "
                             f"Give it as shape ({n}, {len(subset)}) (columns in sensor order).")
        full[:] = L
    else:
        raise ValueError(f"`ObserverSystem(gains=...)`: the gain for sensors {tuple(subset)} has "
                         f"shape {L.shape}; expected ({n}, {len(subset)}) or ({n}, {p}).")
    if not np.all(np.isfinite(full)):
        raise ValueError(f"`ObserverSystem(gains=...)`: the gain for sensors {tuple(subset)} is "
                         f"not finite.")
    return full


@dataclasses.dataclass(frozen=True, eq=False)
class ObserverSystem:
    """A discrete observer in filter form with first-order-hold inputs:

    `x⁻[k] = Phi x[k-1] + B0 u[k-1] + B1 u[k]`,
    `x[k] = x⁻[k] + L_S (y[k] - C x⁻[k] - D u[k])`,

    where `L_S` is the gain for the set `S` of sensors in use at step `k` (all of them
    when nothing is faulted). At `k = 0` the prediction is skipped: `x⁻[0] = x0`.

    Build it with `ObserverSystem.build(Phi, B0, B1, C, D, gains)`. `gains` is either one
    `(n, p)` array (the gain for all sensors; every subset then uses that gain with the
    missing columns deleted, which is not optimal) or a dict from a tuple/frozenset of
    sensor indices to that subset's gain, shape `(n, len(subset))` with columns in sensor
    order. A dict must hold every nonempty subset; the empty set defaults to zero gain
    (pure prediction).

    Fields: `Phi (n, n)`, `B0, B1 (n, m)`, `C (p, n)`, `D (p, m)`, float64, and
    `gain_table (2**p, n, p)`: entry `mask` is the gain of the subset whose bit `j` is
    set for each sensor `j` in it, zero in the other columns.
    """

    Phi: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    C: np.ndarray
    D: np.ndarray
    gain_table: np.ndarray

    @property
    def n_states(self) -> int:
        return self.Phi.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.B0.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.C.shape[0]

    @property
    def full_mask(self) -> int:
        return (1 << self.n_outputs) - 1

    @property
    def L(self) -> np.ndarray:
        """The gain with every sensor in use."""
        return self.gain_table[self.full_mask]

    def gain(self, subset) -> np.ndarray:
        """The `(n, p)` gain used when exactly the sensors in `subset` are in use."""
        return self.gain_table[_subset_mask(subset, self.n_outputs)]

    @classmethod
    def build(cls, Phi, B0, B1, C, D, gains) -> "ObserverSystem":
        Phi, B0, B1, C, D = (np.array(a, dtype=np.float64) for a in (Phi, B0, B1, C, D))
        n = Phi.shape[0] if Phi.ndim == 2 else -1
        if Phi.shape != (n, n) or B0.ndim != 2 or B0.shape[0] != n or B1.shape != B0.shape \
                or C.ndim != 2 or C.shape[1] != n or D.shape != (C.shape[0], B0.shape[1]):
            raise ValueError(f"`ObserverSystem.build` got inconsistent shapes Phi{Phi.shape} "
                             f"B0{B0.shape} B1{B1.shape} C{C.shape} D{D.shape}; expected "
                             f"Phi (n, n), B0 and B1 (n, m), C (p, n), D (p, m).")
        for name, a in dict(Phi=Phi, B0=B0, B1=B1, C=C, D=D).items():
            if not np.all(np.isfinite(a)):
                raise ValueError(f"`ObserverSystem.build`: `{name}` is not finite.")
        p = C.shape[0]
        if p > 8:
            raise ValueError(f"`ObserverSystem.build`: {p} sensors; the gain table (2**p "
                             f"gains) is limited to 8 sensors.")
        table = np.zeros((1 << p, n, p))
        subsets = [list(s) for r in range(1, p + 1) for s in itertools.combinations(range(p), r)]
        if isinstance(gains, dict):
            given = {}
            for key, L in gains.items():
                mask = _subset_mask(key, p)
                given[mask] = _expand_gain(L, [j for j in range(p) if mask >> j & 1], n, p)
            missing = [tuple(s) for s in subsets if _subset_mask(s, p) not in given]
            if missing:
                raise ValueError(f"`ObserverSystem.build(gains=...)` lacks the gains for sensor "
                                 f"subsets {missing}; give one reduced-order gain per nonempty "
                                 f"subset (the fault fallback needs them all).")
            for mask, full in given.items():
                table[mask] = full
        else:
            L = _expand_gain(gains, list(range(p)), n, p)
            for s in subsets:
                table[_subset_mask(s, p)][:, s] = L[:, s]
        return cls(Phi, B0, B1, C, D, table)

    def error_dynamics(self, subset=None) -> np.ndarray:
        """`(I - L C) Phi`, the estimation error's transition matrix for a sensor subset."""
        L = self.L if subset is None else self.gain(subset)
        return (np.eye(self.n_states) - L @ self.C) @ self.Phi
