"""Observer gains by discrete pole placement, robust on stiff thermal networks.

The gain is for the filter ("current estimator") form of `Observer`, whose error obeys
`e[k] = (I − L C) Phi e[k−1]`: its poles are the eigenvalues of `Phi − L (C Phi)`.
`place_observer_gain` places them on the dual pair `(Phiᵀ, (C Phi)ᵀ)` with
`scipy.signal.place_poles` (Kautsky–Nichols–Van Dooren `"KNV0"` or Tits–Yang `"YT"`),
which choose the eigenvectors to make the closed loop as well conditioned as the
requested poles allow (no Ackermann formula: its companion form is hopeless at
stiffness ratios of 10³). `(Phi, C Phi)` and `(Phi, C)` have the same observability
because `Phi = e^{A dt}` is invertible.

The rule for the poles (`observer_poles`): each continuous open-loop thermal
pole `λ_i < 0` moves to `speedup·λ_i` with `speedup` 3…5, then maps to `z = e^{s dt}`.
Two exceptions, both stated in the result:

- a mode already faster than `fastest` (time constant below `min_time_constant`,
  default `5 dt`) is **kept**: its open-loop pole is requested unchanged. The six-node
  IMU's proof mass (τ ≈ 0.094 s, `λ ≈ −10.6 /s`) is such a mode at 10–50 Hz (5 dt is
  0.5–0.1 s): at 20 Hz its open-loop discrete pole is already `e^{−0.53} = 0.59`, its
  estimation error dies within a few samples unaided, and moving it would need large
  gains on a weakly observed state (amplified sensor noise) for nothing.
- a mode whose sped-up time constant would fall below `min_time_constant` is placed
  at `min_time_constant` (capped), spread by 2 % per coincident pole so that no pole
  is repeated more often than there are sensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from .._errors import InputError
from ._observability import observability_rank


@dataclass(frozen=True)
class ObserverPoles:
    """Observer poles chosen by the pole rule (`observer_poles`).

    - `open_loop`: continuous open-loop poles `λ_i` (1/s), ascending in speed.
    - `continuous`: the chosen continuous poles (1/s).
    - `discrete`: `e^{continuous·dt}`, the poles to place.
    - `kept`: per pole, True when the open-loop pole is kept (already faster than
      `min_time_constant`).
    - `capped`: per pole, True when the sped-up pole was limited to `min_time_constant`.
    """

    open_loop: np.ndarray
    continuous: np.ndarray
    discrete: np.ndarray
    kept: tuple[bool, ...]
    capped: tuple[bool, ...]
    dt: float


def observer_poles(system, dt: float, speedup: float = 4.0,
                   min_time_constant: float | None = None) -> ObserverPoles:
    """Discrete observer poles `speedup` times faster than the open-loop thermal poles.

    `s_i = speedup · λ_i` for the continuous poles `λ_i = eig(A)` (real and negative for
    a thermal network), `z_i = e^{s_i dt}`. Modes with open-loop time constant
    `-1/λ_i ≤ min_time_constant` are kept where they are; sped-up poles faster than
    `1/min_time_constant` are capped there (see the module docstring).

    **Arguments:**

    - `system`: the continuous `LinearSystem` (its `A`, 1/s).
    - `dt`: observer sample period (s).
    - `speedup`: the factor, usually 3…5 (default 4). Must be ≥ 1.
    - `min_time_constant`: the fastest observer time constant (s); default `5 dt`.

    **Returns:** an `ObserverPoles`.
    """
    if not speedup >= 1.0:
        raise InputError(f"`observer_poles(speedup={speedup})` must be at least 1: a smaller "
                         "factor asks for an observer slower than the plant.")
    if not dt > 0:
        raise InputError(f"`observer_poles(dt={dt})` must be a positive sample period (s).")
    tau_min = 5.0 * dt if min_time_constant is None else float(min_time_constant)
    lam = np.linalg.eigvals(np.asarray(system.A, float))
    if np.max(np.abs(lam.imag), initial=0.0) > 1e-9 * np.max(np.abs(lam), initial=1.0):
        raise InputError("`observer_poles` needs a system with real open-loop poles (a thermal "
                         "network); give the poles to `place_observer_gain` directly.")
    lam = np.sort(lam.real)[::-1]  # slowest first
    if np.any(lam >= 0):
        raise InputError(f"`observer_poles`: the plant has a pole at {lam.max():.3g} /s (not "
                         "decaying); every node needs a conduction path to a boundary.")
    rate_max = 1.0 / tau_min
    s, kept, capped = [], [], []
    for lam_i in lam:
        if -lam_i >= rate_max:
            s.append(lam_i)
            kept.append(True)
            capped.append(False)
        elif -speedup * lam_i > rate_max:
            s.append(-rate_max)
            kept.append(False)
            capped.append(True)
        else:
            s.append(speedup * lam_i)
            kept.append(False)
            capped.append(False)
    s = np.array(s)
    # Spread coincident poles (the caps) by 2 % each, so each is placed once.
    for i in range(1, len(s)):
        while np.any(np.isclose(s[:i], s[i], rtol=1e-6, atol=0.0)):
            s[i] *= 0.98
    return ObserverPoles(lam, s, np.exp(s * dt), tuple(kept), tuple(capped), float(dt))


def place_observer_gain(system, poles, method: str = "YT", state_names=None,
                        rtol: float = 1e-6) -> np.ndarray:
    """The filter-form observer gain `L` that puts `eig(Phi − L C Phi)` at `poles`.

    Solves the dual state-feedback problem `(Phiᵀ, (C Phi)ᵀ)` with
    `scipy.signal.place_poles` and checks the result.

    **Arguments:**

    - `system`: the `DiscreteSystem` at the observer rate (`Phi`, `C`).
    - `poles`: the discrete poles (inside the unit circle), shape (states,), complex
      ones in conjugate pairs; or an `ObserverPoles`.
    - `method`: `"YT"` (default) or `"KNV0"` (SciPy's robust methods).
    - `state_names`: names for the error messages; default `x0, x1, ...`.
    - `rtol`: the largest relative error of the achieved poles before failing.

    **Returns:** `L`, shape (states, outputs), for `x̂ = x̂⁻ + L (y − C x̂⁻ − D u)`.

    **Raises:** `InputError` (a `ValueError`) when the sensors leave states unobservable
    (naming them and the sensor that would restore them), when a requested pole is
    outside the unit circle or slower than the plant's slowest mode, or when SciPy
    cannot place them (a pole repeated more often than there are sensors).
    """
    if isinstance(poles, ObserverPoles):
        poles = poles.discrete
    Phi, C = np.asarray(system.Phi, float), np.asarray(system.C, float)
    n, p = Phi.shape[0], C.shape[0]
    names = tuple(state_names) if state_names is not None else tuple(f"x{i}" for i in range(n))
    poles = np.atleast_1d(np.asarray(poles))
    if poles.shape != (n,):
        raise InputError(f"`place_observer_gain(poles=...)` needs {n} poles (one per state), "
                         f"got {poles.shape[0] if poles.ndim else 0}.")
    check_observable(system, names, "place_observer_gain")
    if np.max(np.abs(poles)) >= 1.0:
        raise InputError(f"`place_observer_gain(poles=...)` got pole(s) "
                         f"{_fmt(poles[np.abs(poles) >= 1])} on or outside the unit circle: "
                         "the observer error would not decay. Discrete poles are "
                         "`z = exp(s dt)` with `s < 0`.")
    plant = np.max(np.abs(np.linalg.eigvals(Phi)))
    slow = np.abs(poles) > plant * (1 + 1e-9)
    if np.any(slow):
        raise InputError(f"`place_observer_gain(poles=...)`: pole(s) {_fmt(poles[slow])} are "
                         f"slower than the plant's slowest mode (|z| = {plant:.6g}, time "
                         f"constant {-float(system.dt) / math.log(plant):.4g} s): the estimate "
                         "would converge slower than the open-loop model. Ask for poles "
                         "3-5 times faster than the plant's (`observer_poles`).")
    CPhi = C @ Phi
    try:
        result = scipy.signal.place_poles(Phi.T, CPhi.T, poles, method=method)
    except ValueError as err:
        raise InputError(f"`place_observer_gain(method={method!r})` cannot place "
                         f"{_fmt(poles)}: {err} With {p} sensor(s), a pole may repeat at most "
                         f"{p} times; spread repeated poles slightly.") from None
    L = np.asarray(result.gain_matrix).T
    achieved = np.linalg.eigvals(Phi - L @ CPhi)
    err = _pole_mismatch(achieved, poles)
    if err > rtol:
        raise InputError(f"`place_observer_gain` placed the poles with relative error "
                         f"{err:.2g} (over {rtol:g}): the problem is too ill-conditioned at "
                         "these poles. Ask for slower poles, or add a sensor.")
    return L


def check_observable(system, names, call: str) -> None:
    """Raise `InputError` naming the unobservable states and the sensor that restores them."""
    n = np.asarray(system.Phi).shape[0]
    rank = observability_rank(system)
    if rank == n:
        return
    Phi = np.asarray(system.Phi, float)
    C = np.asarray(system.C, float)
    # The unobservable subspace: null space of the block-scaled observability matrix.
    blocks, block = [], C
    for _ in range(n):
        norm = np.linalg.norm(block)
        blocks.append(block / norm if norm > 0 else block)
        block = block @ Phi
    _, s, Vt = np.linalg.svd(np.concatenate(blocks, axis=0))
    null = Vt[rank:].T
    lost = sorted({names[i] for i in range(n) if np.linalg.norm(null[i]) > 0.3})
    restore = []
    for i in range(n):
        extra = np.zeros((1, n))
        extra[0, i] = 1.0
        if np.any(np.all(C == extra, axis=1)):
            continue
        test = _Pair(Phi, np.concatenate([C, extra], axis=0))
        if observability_rank(test) > rank:
            gain = observability_rank(test) - rank
            restore.append((gain, names[i]))
    restore.sort(key=lambda g: -g[0])
    best = [nm for g, nm in restore if g == restore[0][0]] if restore else []
    hint = (f" A sensor on {' or '.join(best)} would restore "
            f"{'them' if restore and restore[0][0] == n - rank else 'the most of them'}."
            if best else "")
    raise InputError(f"`{call}`: the sensors leave {n - rank} of {n} state(s) unobservable "
                     f"(involving {', '.join(lost)}); no gain can place those poles, and no "
                     f"observer can estimate them.{hint}")


@dataclass(frozen=True)
class _Pair:
    Phi: np.ndarray
    C: np.ndarray


def _pole_mismatch(achieved, requested) -> float:
    """Largest relative distance between each requested pole and its nearest achieved one."""
    achieved = list(achieved)
    worst = 0.0
    for z in sorted(requested, key=lambda z: -abs(z)):
        k = int(np.argmin([abs(a - z) for a in achieved]))
        worst = max(worst, abs(achieved.pop(k) - z) / max(abs(z), 1e-12))
    return worst


def _fmt(z) -> str:
    return "[" + ", ".join(f"{complex(v).real:.6g}" if abs(complex(v).imag) < 1e-15
                           else f"{complex(v):.6g}" for v in np.atleast_1d(z)) + "]"

