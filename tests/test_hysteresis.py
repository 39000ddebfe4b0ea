"""Hysteresis loop area: against the exact area of an inscribed polygon of an ellipse and
the analytic loop of a first-order lag integrated separately (scipy)."""

import numpy as np
import pytest
import scipy.integrate

from thermojax._errors import InputError
from thermojax.calibration import hysteresis_loop_area


def test_ellipse_area():
    a, c, n = 30.0, 2.5, 4000  # °C, µg, vertices
    t = 2 * np.pi * np.arange(n) / n
    T, b = 25.0 + a * np.cos(t), 100.0 + c * np.sin(t)
    # An n-gon inscribed in the ellipse (equal parameter steps) has area
    # (n/2) a c sin(2π/n) exactly; float64 roundoff only.
    polygon = 0.5 * n * a * c * np.sin(2 * np.pi / n)
    assert hysteresis_loop_area(T, b, signed=True) == pytest.approx(polygon, rel=1e-12)
    # and tends to π a c (relative error (2π/n)²/6 = 4e-7 here)
    assert hysteresis_loop_area(T, b) == pytest.approx(np.pi * a * c, rel=1e-6)
    # clockwise: the sign flips, the absolute area does not
    assert hysteresis_loop_area(T[::-1], b[::-1], signed=True) == pytest.approx(-polygon,
                                                                                rel=1e-12)
    assert hysteresis_loop_area(T[::-1], b[::-1]) == pytest.approx(polygon, rel=1e-12)


def test_static_relation_encloses_nothing():
    t = np.linspace(0, 2 * np.pi, 2001)
    T = 25 + 60 * np.sin(t)  # there and back along the same curve
    b = 0.5 + 0.03 * (T - 25) + 5e-4 * (T - 25) ** 2
    assert hysteresis_loop_area(T, b) < 1e-9 * 60 * 5  # roundoff only (µg·°C)


def test_first_order_lag_loop():
    """b = k (T − ε), dε/dt = (T − ε)/τ, T = A sin ωt. In the periodic steady state
    ∮ T db = −k ∮ T dε = −π k A² ωτ / (1 + ω²τ²)."""
    A, k, tau, period = 30.0, 0.6, 1500.0, 6000.0  # °C, µg/K, s, s
    w = 2 * np.pi / period
    sol = scipy.integrate.solve_ivp(lambda t, e: (A * np.sin(w * t) - e) / tau,
                                    (0.0, 8 * period), [0.0], method="DOP853",
                                    rtol=1e-12, atol=1e-12, dense_output=True)
    t = 7 * period + np.arange(20000) * period / 20000  # the last period: transient < e^-28
    T = A * np.sin(w * t)
    b = k * (T - sol.sol(t)[0])
    expected = -np.pi * k * A ** 2 * w * tau / (1 + (w * tau) ** 2)
    # polygon of 20000 vertices: discretization ~ (2π/20000)² ~ 1e-7 relative
    assert hysteresis_loop_area(T, b, signed=True) == pytest.approx(expected, rel=1e-6)


def test_nan_pairs_dropped_and_bad_input():
    t = 2 * np.pi * np.arange(1000) / 1000
    T, b = np.cos(t), np.sin(t)
    b_gap = b.copy()
    b_gap[10] = np.nan
    T_gap = T.copy()
    T_gap[10] = np.nan
    # dropping one vertex of 1000 changes the polygon by one sliver (~1e-8)
    assert hysteresis_loop_area(T, b_gap) == pytest.approx(hysteresis_loop_area(T, b), rel=1e-6)
    assert hysteresis_loop_area(T_gap, b) == pytest.approx(hysteresis_loop_area(T, b), rel=1e-6)
    with pytest.raises(InputError, match="equally long"):
        hysteresis_loop_area(T, b[:-1])
    with pytest.raises(InputError, match="at least 3 finite"):
        hysteresis_loop_area([1.0, np.nan, 2.0], [0.0, 1.0, np.nan])
