"""The JAX observer: the documented filter-form equations, jit, vmap, gradients.

Truths: a NumPy loop of the module docstring's three lines; a time-varying Kalman filter
in NumPy started at the steady-state covariance (which then stays there, so it must
equal the constant-gain observer); central finite differences.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import thermojax as tj
from thermojax import observer as ob
from thermojax.model import ThermalModel

from helpers import CONFIGS, model_matrices, np_discretize, np_simulate


def imu_data(steps=400, seed=0, dt=0.05):
    """Noisy readings of the imu6 model (process and sensor noise), NumPy only."""
    m = model_matrices(CONFIGS / "imu6.toml")
    rng = np.random.default_rng(seed)
    ts = dt * np.arange(steps)
    U = np.stack([25 + 5 * np.sin(ts / 7.0), 0.2 * (ts > 3.0)], axis=1)
    X, Y = np_simulate(m["A"], m["B"], m["Cy"], np.full(6, 25.0), U, dt, m["holds"])
    return m, U, Y + 0.01 * rng.standard_normal(Y.shape)


def np_observer(Phi, B0, B1, C, D, L, U, Y, x0):
    xs, preds, rs = [], [], []
    x = None
    for k in range(U.shape[0]):
        xp = x0 if k == 0 else Phi @ x + B0 @ U[k - 1] + B1 @ U[k]
        r = Y[k] - C @ xp - D @ U[k]
        x = xp + L @ r
        xs.append(x), preds.append(xp), rs.append(r)
    return np.array(xs), np.array(preds), np.array(rs)


def test_run_observer_is_the_documented_recursion():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    obs = ob.design_observer(model, 0.05)
    m, U, Y = imu_data()
    x0 = np.full(6, 24.0)
    run = jax.jit(ob.run_observer)(obs, jnp.asarray(U), jnp.asarray(Y), jnp.asarray(x0))
    s = obs.system
    Phi, B0, B1 = np_discretize(m["A"], m["B"], 0.05, m["holds"])
    np.testing.assert_allclose(np.asarray(s.Phi), Phi, rtol=1e-12, atol=1e-15)  # expm vs scipy
    ref = np_observer(*(np.asarray(a) for a in (s.Phi, s.B0, s.B1, s.C, s.D, obs.gain)),
                      U, Y, x0)
    # identical arithmetic up to summation order: 1e-12 °C at ~25 °C
    for got, want in zip((run.states, run.predicted, run.innovations), ref):
        np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-10)
    # step() is one iteration of the same recursion
    x1 = obs.step(run.states[0], jnp.asarray(U[0]), jnp.asarray(U[1]), jnp.asarray(Y[1]))
    np.testing.assert_allclose(np.asarray(x1), ref[0][1], atol=1e-12)


def test_constant_gain_equals_kalman_filter_at_steady_state():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    system = model.linear_system()
    d = tj.discretize(system, 0.05)
    Qd = ob.discrete_process_covariance(system.A, np.asarray(model.process_noise), 0.05)
    R = np.diag(np.asarray(model.noise) ** 2)
    kg = ob.steady_state_kalman(d, Qd, np.diag(R))
    m, U, Y = imu_data(steps=300, seed=3)
    x0 = np.full(6, 25.0)
    Phi, B0, B1 = np_discretize(m["A"], m["B"], 0.05, m["holds"])
    C = m["Cy"]
    # time-varying Kalman filter in NumPy, its covariance started at the steady state
    x, P = x0, kg.predicted_covariance
    xs = []
    for k in range(U.shape[0]):
        if k:
            x = Phi @ x + B0 @ U[k - 1] + B1 @ U[k]
            P = Phi @ Pf @ Phi.T + Qd
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x = x + K @ (Y[k] - C @ x)
        Pf = (np.eye(6) - K @ C) @ P
        xs.append(x)
    run = ob.run_observer(ob.Observer(d, jnp.asarray(kg.gain)), jnp.asarray(U), jnp.asarray(Y),
                          jnp.asarray(x0))
    np.testing.assert_allclose(np.asarray(run.states), np.array(xs), rtol=0, atol=1e-9)


def test_vmap_over_runs():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    obs = ob.design_observer(model, 0.05)
    data = [imu_data(steps=200, seed=s) for s in range(3)]
    U = jnp.asarray(np.stack([d[1] for d in data]))
    Y = jnp.asarray(np.stack([d[2] for d in data]))
    X0 = jnp.asarray(np.stack([np.full(6, 24.0 + s) for s in range(3)]))
    batched = jax.vmap(ob.run_observer, in_axes=(None, 0, 0, 0))(obs, U, Y, X0)
    for i in range(3):
        one = ob.run_observer(obs, U[i], Y[i], X0[i])
        np.testing.assert_allclose(np.asarray(batched.states[i]), np.asarray(one.states),
                                   rtol=0, atol=1e-12)  # same ops, batched


def test_gradient_through_discretization_and_gain_vs_finite_differences():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    obs = ob.design_observer(model, 0.05)
    _, U, Y = imu_data(steps=120)
    U, Y = jnp.asarray(U), jnp.asarray(Y)
    x0 = jnp.full(6, 24.0)
    gain = obs.gain

    def loss(log_c, L):
        net = eqx.tree_at(lambda n: n.log_capacitance, model.network, log_c)
        o = ob.Observer(tj.discretize(net.linear_system(), 0.05), L)
        return jnp.sum(ob.run_observer(o, U, Y, x0).innovations ** 2)

    log_c = model.network.log_capacitance
    g_c, g_L = jax.grad(loss, argnums=(0, 1))(log_c, gain)
    # h = 1e-4: the O(h²) truncation (~1e-8 relative) is below the exponential's
    # roundoff amplified by 1/h at smaller steps (1e-5 relative at h = 1e-6)
    h = 1e-4
    for i in range(6):
        e = jnp.zeros(6).at[i].set(h)
        fd = (loss(log_c + e, gain) - loss(log_c - e, gain)) / (2 * h)
        np.testing.assert_allclose(float(g_c[i]), float(fd), rtol=2e-6, atol=1e-9)
    for i, j in [(0, 0), (5, 2), (3, 1)]:
        # the loss is a high-degree polynomial in L (no exponential): a fourth-order
        # central difference at 1e-5, whose roundoff (~1e-11 relative) and truncation are
        # far below the tolerance (two points at 1e-7 carried ~1e-6 of roundoff)
        hL = 1e-5
        E = jnp.zeros((6, 3)).at[i, j].set(hL)
        fd = (8 * (loss(log_c, gain + E) - loss(log_c, gain - E))
              - (loss(log_c, gain + 2 * E) - loss(log_c, gain - 2 * E))) / (12 * hL)
        np.testing.assert_allclose(float(g_L[i, j]), float(fd), rtol=1e-6, atol=1e-9)


def test_observer_errors():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    obs = ob.design_observer(model, 0.05)
    with pytest.raises(ValueError, match=r"`Observer\(gain=...\)` needs shape \(6, 3\)"):
        ob.Observer(obs.system, jnp.zeros((6, 2)))
    with pytest.raises(ValueError, match="as many input samples as readings"):
        ob.run_observer(obs, jnp.zeros((5, 2)), jnp.zeros((4, 3)), jnp.zeros(6))
