"""Simulation: `simulate`, `simulate_batch`, `ExactHold` (scan and associative scan), `DiffraxSimulator`.

Every numerical check compares against a truth computed without the code under
test: closed-form solutions of one- and two-node networks, `scipy.signal.lsim`
(one input at a time, each with its own hold, summed by superposition) and
`scipy.integrate.solve_ivp(method="Radau")` integrated sample interval by sample
interval. The reference state-space matrices are assembled in NumPy straight from
the TOML files (`tomllib`), not through `ThermalNetwork`.
"""

import tomllib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
import scipy.signal
from jax.flatten_util import ravel_pytree

import thermojax as tj

from helpers import CONFIGS, as_np, imu6, random_network, rtd2


# ---------------------------------------------------------------------------------------------
# Independent references (NumPy / SciPy only).
# ---------------------------------------------------------------------------------------------


def _toml_matrices(name: str) -> dict:
    """`K`, `G`, `c`, `A = -K/c`, `B = G/c`, sensor matrix and holds, read from the TOML file.

    `C dT/dt = -K T + G u`: links add the Laplacian, boundaries add `g` to `K[i, i]` and to
    `G[i, input]`, heat inputs add their gain to `G[i, input]`. Input order is the order of
    first appearance (boundaries, then heat inputs), as the model-file spec defines it.
    """
    doc = tomllib.loads((CONFIGS / name).read_text())

    def val(v):
        return v["value"] if isinstance(v, dict) else v

    names = [node["name"] for node in doc["nodes"]]
    idx = {n: i for i, n in enumerate(names)}
    n = len(names)
    c = np.array([val(node["capacitance"]) for node in doc["nodes"]], dtype=float)
    K = np.zeros((n, n))
    for link in doc.get("links", []):
        i, j = (idx[x] for x in link["between"])
        g = val(link["conductance"])
        K[i, i] += g
        K[j, j] += g
        K[i, j] -= g
        K[j, i] -= g
    inputs, holds = [], []
    for entry in doc.get("boundaries", []) + doc.get("heat_inputs", []):
        if entry["input"] not in inputs:
            inputs.append(entry["input"])
            holds.append(entry.get("hold", "foh"))
    G = np.zeros((n, len(inputs)))
    for b in doc.get("boundaries", []):
        i, g = idx[b["node"]], val(b["conductance"])
        K[i, i] += g
        G[i, inputs.index(b["input"])] += g
    for h in doc.get("heat_inputs", []):
        G[idx[h["node"]], inputs.index(h["input"])] += val(h.get("gain", 1.0))
    Cy = np.zeros((len(doc["sensors"]), n))
    for k, s in enumerate(doc["sensors"]):
        Cy[k, idx[s["node"]]] = 1.0
    return dict(c=c, K=K, G=G, A=-K / c[:, None], B=G / c[:, None], Cy=Cy,
                inputs=tuple(inputs), holds=tuple(holds))


def _lsim_states(A, B, holds, U, ts, x0):
    """States at `ts` by `scipy.signal.lsim`, one input at a time with its own hold, summed."""
    n = A.shape[0]
    states = np.zeros((len(ts), n))
    for j, hold in enumerate(holds):
        sys_j = (A, B[:, j:j + 1], np.eye(n), np.zeros((n, 1)))
        _, _, x = scipy.signal.lsim(sys_j, U[:, j], ts, X0=x0 if j == 0 else None,
                                    interp=(hold == "foh"))
        states += x.reshape(len(ts), n)
    return states


def _radau_states(A, B, holds, U, ts, x0, tol=1e-12):
    """States at `ts` by Radau, one sample interval at a time, so that every kink (FOH) and
    jump (ZOH) of the input lies on an integration boundary."""
    zoh = np.array([h == "zoh" for h in holds])
    x = np.asarray(x0, dtype=float)
    out = [x]
    for k in range(len(ts) - 1):
        t0, t1, u0, u1 = ts[k], ts[k + 1], U[k], U[k + 1]

        def f(t, x, t0=t0, t1=t1, u0=u0, u1=u1):
            u = np.where(zoh, u0, u0 + (t - t0) / (t1 - t0) * (u1 - u0))
            return A @ x + B @ u

        sol = scipy.integrate.solve_ivp(f, (t0, t1), x, method="Radau", rtol=tol, atol=tol,
                                        jac=A)
        assert sol.success
        x = sol.y[:, -1]
        out.append(x)
    return np.array(out)


def _imu6_profile(n: int = 300, dt: float = 1.0, seed: int = 0):
    """Chamber soak-ramp-soak-ramp (piecewise linear, °C) plus a PRBS ASIC power (W)."""
    ts = dt * np.arange(n)
    t_end = ts[-1]
    chamber = np.interp(ts, [0.0, 0.15 * t_end, 0.5 * t_end, 0.65 * t_end, t_end],
                        [20.0, 20.0, 60.0, 60.0, 40.0])
    rng = np.random.default_rng(seed)
    bits = rng.integers(0, 2, size=-(-n // 7))
    power = 0.05 * np.repeat(bits, 7)[:n].astype(float)
    return ts, np.stack([chamber, power], axis=1)


IMU6_X0 = np.array([15.0, 18.0, 21.0, 30.0, 27.0, 24.0])  # far from equilibrium: all modes ring


def _one_node(capacitance: float, conductance: float, hold: str) -> tj.ThermalNetwork:
    topo = tj.Topology(node_names=("n",), links=(), boundary_nodes=(0,), boundary_inputs=(0,),
                       heat_nodes=(), heat_inputs=(), input_names=("T_amb",),
                       input_holds=(hold,), sensor_nodes=(0,), sensor_names=("T",))
    return tj.ThermalNetwork.from_physical(topo, capacitance=[capacitance],
                                           conductance=np.zeros(0),
                                           boundary_conductance=[conductance])


# ---------------------------------------------------------------------------------------------
# 1-2. One node: analytic step and ramp; FOH exact, ZOH lags half a sample.
# ---------------------------------------------------------------------------------------------

ONE_C, ONE_G = 2.0, 0.5  # J/K, W/K: tau = 4 s
ONE_TAU = ONE_C / ONE_G
ONE_N = 1601  # one length for every one-node run: the scan compiles once


@pytest.mark.parametrize("hold", ["foh", "zoh"])
@pytest.mark.parametrize("parallel", [False, True])
def test_one_node_step_analytic(hold, parallel):
    t_amb, t0, dt = 20.0, 80.0, 0.1
    ts = dt * np.arange(ONE_N)
    u = np.full((ts.size, 1), t_amb)
    sol = tj.simulate(_one_node(ONE_C, ONE_G, hold), u, ts, x0=np.array([t0]),
                      simulator=tj.ExactHold(parallel=parallel))
    exact = t_amb + (t0 - t_amb) * np.exp(-ts / ONE_TAU)
    # Exact for a constant input under either hold; 400 steps of float64 roundoff on ~50 °C.
    np.testing.assert_allclose(as_np(sol.states)[:, 0], exact, rtol=1e-13, atol=0)
    np.testing.assert_allclose(as_np(sol.outputs)[:, 0], exact, rtol=1e-13, atol=0)
    np.testing.assert_array_equal(as_np(sol.ts), ts)


def _ramp_foh_exact(ts, a, b, x0, tau):
    """`tau dT/dt = a + b t - T`, `T(0) = x0`: `T = a + b (t - tau) + (x0 - a + b tau) e^{-t/tau}`."""
    return a + b * (ts - tau) + (x0 - a + b * tau) * np.exp(-ts / tau)


def _ramp_zoh_exact(ts, a, b, x0, tau, dt):
    """The same network driven by the staircase `u(t) = a + b t_k` on `[t_k, t_k + dt)`.

    `x[k+1] = phi x[k] + (1 - phi) u[k]` with `phi = e^{-dt/tau}` has the particular solution
    `a + b t_k - b dt / (1 - phi)`, so `x[k] = a + b t_k - lag + (x0 - a + lag) phi^k`.
    """
    phi = np.exp(-dt / tau)
    lag = b * dt / -np.expm1(-dt / tau)
    return a + b * ts - lag + (x0 - a + lag) * phi ** np.arange(ts.size)


@pytest.mark.parametrize("dt", [0.05, 0.5, 2.0])
def test_one_node_ramp_foh_is_exact(dt):
    a, b, x0 = 10.0, 0.3, 35.0  # °C, K/s, °C
    ts = dt * np.arange(ONE_N)
    u = (a + b * ts)[:, None]
    sol = tj.simulate(_one_node(ONE_C, ONE_G, "foh"), u, ts, x0=np.array([x0]))
    # FOH is exact for an input linear between samples: float64 roundoff on ~30 °C only.
    np.testing.assert_allclose(as_np(sol.states)[:, 0], _ramp_foh_exact(ts, a, b, x0, ONE_TAU),
                               rtol=1e-12, atol=0)


@pytest.mark.parametrize("dt", [0.05, 0.5, 2.0])
def test_one_node_ramp_zoh_lags_half_a_sample(dt):
    a, b, x0 = 10.0, 0.3, 35.0
    ts = dt * np.arange(ONE_N)  # >= 20 tau: the transient is below e^-20 ~ 2e-9
    u = (a + b * ts)[:, None]
    foh = as_np(tj.simulate(_one_node(ONE_C, ONE_G, "foh"), u, ts, x0=np.array([x0])).states)
    zoh = as_np(tj.simulate(_one_node(ONE_C, ONE_G, "zoh"), u, ts, x0=np.array([x0])).states)
    # ZOH is exact for the staircase it assumes: float64 roundoff only.
    np.testing.assert_allclose(zoh[:, 0], _ramp_zoh_exact(ts, a, b, x0, ONE_TAU, dt),
                               rtol=1e-12, atol=0)
    # In the steady ramp the ZOH model trails the FOH one by b (dt / (1 - e^{-dt/tau}) - tau)
    # = b dt/2 (1 + dt/(6 tau) + O(dt^3)): half a sample of the ramp.
    lag = b * (dt / -np.expm1(-dt / ONE_TAU) - ONE_TAU)
    steady = foh[-1, 0] - zoh[-1, 0]
    # Remaining transient (x0 - a + lag) e^{-20} ~ 1e-7 plus roundoff.
    assert abs(steady - lag) < 1e-6
    # The half-sample rule holds to the next Taylor term b dt^2 / (12 tau) (+ 1 % for O(dt^3)).
    assert abs(steady - b * dt / 2) <= 1.01 * b * dt ** 2 / (12 * ONE_TAU) + 1e-6
