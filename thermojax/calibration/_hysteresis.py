"""The area of a bias-versus-temperature hysteresis loop (shoelace formula).

NumPy only.
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError


def hysteresis_loop_area(temperature, bias, *, signed: bool = False) -> float:
    """The area enclosed by the bias-versus-temperature trajectory of a thermal cycle.

    The trajectory `(T_i, b_i)` is taken as a closed polygon (the shoelace formula),

        A = ½ Σ_i (T_i b_{i+1} − T_{i+1} b_i),   the index taken cyclically,

    which is the line integral `∮ T db = −∮ b dT` along the path. It is positive when
    the path runs counter-clockwise with temperature on the x-axis and bias on the
    y-axis. A static (single-valued) relation `b = p(T)` encloses nothing: its
    `∮ p(T) dT` vanishes over a closed cycle, so the loop area of `b − p(T)` is the
    area of `b` for every polynomial `p` in the same temperature. A lag of the bias
    behind the temperature (a viscoelastic strain) opens a loop whose area grows with
    the lag.

    The polygon is closed by the chord from the last sample back to the first: run the
    cycle back to its starting temperature (and let it settle) so that this chord is
    short. Samples where either value is not finite are dropped. The data are centred
    before the sum, which changes nothing in exact arithmetic and keeps the roundoff of
    the products small.

    **Arguments:**

    - `temperature`: `(samples,)` °C along the cycle.
    - `bias`: `(samples,)` the bias in its unit (deg/h, µg, ...).
    - `signed`: return the signed area (counter-clockwise positive) instead of its
      absolute value. Lobes of a figure-eight enclose opposite signs and cancel: the
      result is the net area.

    **Returns:** the area, in bias unit × °C (e.g. µg·°C).
    """
    T = np.asarray(temperature, dtype=float)
    b = np.asarray(bias, dtype=float)
    if T.ndim != 1 or T.shape != b.shape:
        raise InputError(f"`hysteresis_loop_area(temperature, bias)` needs two equally long "
                         f"columns, got shapes {T.shape} and {b.shape}.", field="bias")
    ok = np.isfinite(T) & np.isfinite(b)
    if ok.sum() < 3:
        raise InputError(f"`hysteresis_loop_area` needs at least 3 finite (temperature, bias) "
                         f"pairs to enclose an area, got {int(ok.sum())}.", field="bias")
    x = T[ok] - T[ok].mean()
    y = b[ok] - b[ok].mean()
    area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return area if signed else abs(area)
