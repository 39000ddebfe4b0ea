"""The extended Kalman filter's fourth-order step (`dynamics._etdrk4`): exact on a linear
model (against the augmented-matrix exponential written here with SciPy) and fourth order
on a nonlinear one (against its equations written here in NumPy, solved by SciPy).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from thermojax import ThermalModel, parse_model
from thermojax.dynamics._etdrk4 import etdrk4_step, phi_functions

from hidden import generator as g


def test_phi_functions_are_their_series():
    """`φ_k(z) = Σ_j z^j / (j + k)!`, summed here term by term on a small matrix."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    h = 0.3
    got = [np.asarray(m) for m in phi_functions(jnp.asarray(A), h)]
    Z = h * A
    for k in range(4):
        term, total = np.eye(3) / np.prod(np.arange(1, k + 1)), np.zeros((3, 3))
        for j in range(40):
            total += term
            term = term @ Z / (j + k + 1)
        np.testing.assert_allclose(got[k], total, rtol=1e-12, atol=1e-14)


def test_a_linear_step_is_the_exact_discretization():
    """Without nonlinear effects one step is the exact solution with the chamber ramped
    (first-order hold) and the power held (zero-order hold): SciPy's `expm` of
    `[[A, B, 0], [0, 0, I/h], [0, 0, 0]] h`."""
    spec = parse_model((g.REPO / "thermojax" / "data" / "chain3.toml").read_text())
    model = ThermalModel.from_spec(spec)
    system = model.linear_system()
    A, B = np.asarray(system.A), np.asarray(system.B)
    n, m = B.shape
    holds = np.array([h == "foh" for h in system.holds])
    assert holds.any() and not holds.all()  # one of each
    h = 7.0
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n], M[:n, n:n + m], M[n:n + m, n + m:] = A, B, np.eye(m) / h
    E = scipy.linalg.expm(M * h)
    x, u0, u1 = np.array([30.0, 35.0, 41.0]), np.array([25.0, 0.4]), np.array([27.0, 0.9])
    want = E[:n, :n] @ x + E[:n, n:n + m] @ u0 + E[:n, n + m:] @ ((u1 - u0) * holds)
    for substeps in (1, 3):
        got = etdrk4_step(model, system, h, substeps)(jnp.asarray(x), jnp.asarray(u0),
                                                    jnp.asarray(u1))
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-13, atol=1e-12)


# Two nodes, a link whose conductance follows its mean temperature, the chamber ramped
# (first-order hold) into node a, a power held (zero-order hold) into node b; time
# constants of 20-100 s at 60 s samples, so that the step's error is far above SciPy's.
TWO_NODES = """
name = "two"
[[nodes]]
name = "a"
capacitance = 50.0
[[nodes]]
name = "b"
capacitance = 20.0
[[links]]
between = ["a", "b"]
conductance = 0.5
[[boundaries]]
node = "a"
input = "T_chamber"
conductance = 0.4
[[heat_inputs]]
node = "b"
input = "P"
gain = { value = 1.0, fixed = true }
hold = "zoh"
[[sensors]]
node = "b"
column = "T_b"
[[effects]]
kind = "conductance_temperature"
where = ["a", "b"]
alpha = 0.03
"""


def _two_nodes_by_scipy(x0, ts, T_chamber, P):
    """States (T, 2) of `TWO_NODES` written out here in NumPy, by SciPy's DOP853 at
    rtol 1e-13 sample period by sample period."""
    from scipy.integrate import solve_ivp

    def rhs(t, x, k):
        s = (t - ts[k]) / (ts[k + 1] - ts[k])
        Tc = T_chamber[k] + s * (T_chamber[k + 1] - T_chamber[k])
        g = 0.5 * (1 + 0.03 * (0.5 * (x[0] + x[1]) - 25.0))
        return [(g * (x[1] - x[0]) + 0.4 * (Tc - x[0])) / 50.0,
                (g * (x[0] - x[1]) + P[k]) / 20.0]

    xs = [np.asarray(x0, float)]
    for k in range(len(ts) - 1):
        sol = solve_ivp(rhs, (ts[k], ts[k + 1]), xs[-1], method="DOP853", rtol=1e-13,
                        atol=1e-12, args=(k,))
        xs.append(sol.y[:, -1])
    return np.array(xs)


def test_the_step_is_fourth_order():
    """Halving the substep divides the error of a free run against SciPy by about 16 (a
    fifth-order local error summed over the steps; 11.5 from 1 to 2 substeps, before the
    asymptote)."""
    dt = 60.0
    model = ThermalModel.from_spec(parse_model(TWO_NODES))
    system = model.linear_system()
    assert [h for h in system.holds] == ["foh", "zoh"]
    rng = np.random.default_rng(1)
    ts = dt * np.arange(25)
    T_chamber = 25.0 + np.cumsum(rng.uniform(-10.0, 10.0, ts.size))
    P = rng.choice([0.0, 2.0], ts.size)
    x0 = np.array([30.0, 45.0])
    want = _two_nodes_by_scipy(x0, ts, T_chamber, P)
    u = jnp.asarray(np.stack([T_chamber, P], 1))
    errors = []
    for substeps in (2, 4, 8):
        step = etdrk4_step(model, system, dt, substeps)
        xs = jax.lax.scan(lambda x, k: (step(x, u[k], u[k + 1]), x), jnp.asarray(x0),
                          jnp.arange(ts.size - 1))[1]
        errors.append(float(np.max(np.abs(np.asarray(xs) - want[:-1]))))
    assert errors[-1] > 1e-9  # far above SciPy's error
    ratios = [errors[i] / errors[i + 1] for i in range(2)]
    assert all(13.0 < r < 19.0 for r in ratios), (errors, ratios)
