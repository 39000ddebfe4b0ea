"""Simulation: `simulate`, `simulate_batch`, `ExactHold` (scan and associative scan), `DiffraxSimulator`.

Every numerical check compares against a truth computed without the code under
test: closed-form solutions of one- and two-node networks, `scipy.signal.lsim`
(one input at a time, each with its own hold, summed by superposition) and
`scipy.integrate.solve_ivp(method="Radau")` integrated sample interval by sample
interval. The reference state-space matrices are assembled in NumPy straight from
the TOML files (`tomllib`), not through `ThermalNetwork`.
"""

import functools
import tomllib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
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


# Jitted once per input shape and model structure (eager dispatch recompiles the scan on every
# call); the eager path itself is checked in `test_jit_matches_eager`.
simulate = eqx.filter_jit(tj.simulate)

IMU6_X0 = np.array([15.0, 18.0, 21.0, 30.0, 27.0, 24.0])  # far from equilibrium: all modes ring


def _one_node(capacitance: float, conductance: float, hold: str) -> tj.ThermalNetwork:
    topo = tj.Topology(node_names=("n",), links=(), boundary_nodes=(0,), boundary_inputs=(0,),
                       heat_nodes=(), heat_inputs=(), input_names=("T_amb",),
                       input_holds=(hold,), sensor_nodes=(0,), sensor_names=("T",))
    return tj.ThermalNetwork.from_physical(topo, capacitance=[capacitance],
                                           conductance=np.zeros(0),
                                           boundary_conductance=[conductance])




@functools.cache
def _imu6_reference(kind: str):
    """`(ts, U, states)` for the imu6 profile from `x0 = IMU6_X0`, by `lsim` or by Radau."""
    m = _toml_matrices("imu6.toml")
    assert m["inputs"] == ("T_chamber", "P_asic") and m["holds"] == ("foh", "zoh")
    ts, U = _imu6_profile()
    ref = _lsim_states if kind == "lsim" else _radau_states
    return ts, U, ref(m["A"], m["B"], m["holds"], U, ts, IMU6_X0)


# ---------------------------------------------------------------------------------------------
# 1-2. One node: analytic step and ramp; FOH exact, ZOH lags half a sample.
# ---------------------------------------------------------------------------------------------

ONE_C, ONE_G = 2.0, 0.5  # J/K, W/K: tau = 4 s
ONE_TAU = ONE_C / ONE_G
ONE_N = 1601  # one length for every one-node run: each program compiles once


@pytest.mark.parametrize("hold, parallel", [("foh", False), ("zoh", False), ("foh", True)])
def test_one_node_step_analytic(hold, parallel):
    t_amb, t0, dt = 20.0, 80.0, 0.1
    ts = dt * np.arange(ONE_N)
    u = np.full((ts.size, 1), t_amb)
    sol = simulate(_one_node(ONE_C, ONE_G, hold), u, ts, x0=np.array([t0]),
                   simulator=tj.ExactHold(parallel=parallel))
    exact = t_amb + (t0 - t_amb) * np.exp(-ts / ONE_TAU)
    # Exact for a constant input under either hold; float64 roundoff only (measured 9e-15).
    np.testing.assert_allclose(as_np(sol.states)[:, 0], exact, rtol=1e-13, atol=0)
    np.testing.assert_allclose(as_np(sol.outputs)[:, 0], exact, rtol=1e-13, atol=0)
    np.testing.assert_array_equal(as_np(sol.ts), ts)


def _ramp_foh_exact(ts, a, b, x0, tau):
    """`tau dT/dt = a + b t - T`, `T(0) = x0`: `T = a + b (t - tau) + (x0 - a + b tau) e^{-t/tau}`."""
    return a + b * (ts - tau) + (x0 - a + b * tau) * np.exp(-ts / tau)


def _ramp_zoh_exact(ts, a, b, x0, tau, dt):
    """The same node driven by the staircase `u(t) = a + b t_k` on `[t_k, t_k + dt)`.

    `x[k+1] = phi x[k] + (1 - phi) u[k]` with `phi = e^{-dt/tau}` has the particular solution
    `a + b t_k - lag`, `lag = b dt / (1 - phi)`, so `x[k] = a + b t_k - lag + (x0 - a + lag) phi^k`.
    """
    lag = b * dt / -np.expm1(-dt / tau)
    return a + b * ts - lag + (x0 - a + lag) * np.exp(-ts / tau)


RAMP = dict(a=10.0, b=0.3, x0=35.0)  # °C, K/s, °C


@pytest.mark.parametrize("dt", [0.05, 0.5, 2.0])
def test_one_node_ramp_foh_is_exact(dt):
    ts = dt * np.arange(ONE_N)
    u = (RAMP["a"] + RAMP["b"] * ts)[:, None]
    sol = simulate(_one_node(ONE_C, ONE_G, "foh"), u, ts, x0=np.array([RAMP["x0"]]))
    # FOH is exact for an input linear between samples: float64 roundoff only (measured 9e-15
    # relative; the state grows to ~1000 °C over the longest run).
    np.testing.assert_allclose(as_np(sol.states)[:, 0], _ramp_foh_exact(ts, tau=ONE_TAU, **RAMP),
                               rtol=1e-12, atol=0)


@pytest.mark.parametrize("dt", [0.05, 0.5, 2.0])
def test_one_node_ramp_zoh_lags_half_a_sample(dt):
    ts = dt * np.arange(ONE_N)  # >= 80 s = 20 tau: the transient is below e^-20 ~ 2e-9
    u = (RAMP["a"] + RAMP["b"] * ts)[:, None]
    x0 = np.array([RAMP["x0"]])
    foh = as_np(simulate(_one_node(ONE_C, ONE_G, "foh"), u, ts, x0=x0).states)[:, 0]
    zoh = as_np(simulate(_one_node(ONE_C, ONE_G, "zoh"), u, ts, x0=x0).states)[:, 0]
    # ZOH is exact for the staircase it assumes: float64 roundoff only (measured 9e-15 relative).
    np.testing.assert_allclose(zoh, _ramp_zoh_exact(ts, tau=ONE_TAU, dt=dt, **RAMP),
                               rtol=1e-12, atol=0)
    # On the steady ramp the ZOH model trails the true (FOH) response by
    # b (dt / (1 - e^{-dt/tau}) - tau) = b dt/2 (1 + dt/(6 tau) + O(dt^3)): half a sample.
    b = RAMP["b"]
    lag = b * (dt / -np.expm1(-dt / ONE_TAU) - ONE_TAU)
    steady = foh[-1] - zoh[-1]
    # What is left of the transient (~40 K e^{-20} = 8e-8) plus roundoff on ~1000 °C.
    assert abs(steady - lag) < 1e-6
    # Half a sample, up to the next Taylor term b dt^2 / (12 tau) (1 % more covers O(dt^3)).
    assert abs(steady - b * dt / 2) <= 1.01 * b * dt ** 2 / (12 * ONE_TAU) + 1e-6
    assert steady > 0.49 * b * dt


# ---------------------------------------------------------------------------------------------
# 3-4. Mixed holds on imu6 (T_chamber FOH, P_asic ZOH) against SciPy; every ExactHold path.
# ---------------------------------------------------------------------------------------------


def test_references_agree():
    """The two SciPy references are independent of each other (expm vs Radau)."""
    _, _, lsim = _imu6_reference("lsim")
    _, _, radau = _imu6_reference("radau")
    # Radau at rtol = atol = 1e-12 on each interval; measured 5e-13.
    np.testing.assert_allclose(lsim, radau, rtol=0, atol=1e-10)


def _dense(system: tj.LinearSystem) -> tj.LinearSystem:
    """The same system without `capacitance`: a general LTI system (the dense associative path)."""
    return tj.LinearSystem(system.A, system.B, system.C, system.D, holds=system.holds)


EXACT_PATHS = {
    "scan": (lambda net: net, tj.ExactHold()),
    "modal-discretization": (lambda net: net, tj.ExactHold(discretization=tj.Modal())),
    "parallel-modal": (lambda net: net, tj.ExactHold(parallel=True)),
    "parallel-dense": (lambda net: _dense(net.linear_system()), tj.ExactHold(parallel=True)),
}


@pytest.mark.parametrize("path", [
    pytest.param(p, marks=pytest.mark.slow) if p == "modal-discretization" else p
    for p in EXACT_PATHS])
def test_imu6_mixed_holds_match_scipy(path):
    model_of, simulator = EXACT_PATHS[path]
    m = _toml_matrices("imu6.toml")
    for reference in ["lsim", "radau"]:
        ts, U, expected = _imu6_reference(reference)
        sol = simulate(model_of(imu6()), U, ts, x0=IMU6_X0, simulator=simulator)
        # Every path is an exact discretization of the same holds; paths and references differ
        # by float64 roundoff only (measured <= 2e-12 on 15-60 °C). The parallel paths reassociate
        # the same products (O(log T) rather than O(T) roundoff): same tolerance as the scan.
        np.testing.assert_allclose(as_np(sol.states), expected, rtol=1e-9, atol=1e-9)
        # Outputs are the sensor rows of the states: same roundoff.
        np.testing.assert_allclose(as_np(sol.outputs), expected @ m["Cy"].T, rtol=1e-9,
                                   atol=1e-9)


def test_imu6_holds_matter():
    """The comparison above tells the holds apart: the wrong hold on either input is far off."""
    ts, U, expected = _imu6_reference("lsim")
    m = _toml_matrices("imu6.toml")
    got = as_np(simulate(imu6(), U, ts, x0=IMU6_X0).states)
    for wrong in [("zoh", "zoh"), ("foh", "foh")]:
        other = _lsim_states(m["A"], m["B"], wrong, U, ts, IMU6_X0)
        # A swapped hold moves the states by 0.06 K (chamber as ZOH) or 0.28 K (ASIC power as
        # FOH), measured: the 1e-3 K threshold is 1e6 x the 1e-9 tolerance above.
        assert np.abs(got - other).max() > 1e-3
    # As in test_imu6_mixed_holds_match_scipy.
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)


def _numpy_matrices(net: tj.ThermalNetwork):
    """`A`, `B`, `K`, `G` assembled in NumPy from a network's physical values and topology."""
    t = net.topology
    c, g, gb, gh = (as_np(v) for v in (net.capacitance, net.conductance,
                                       net.boundary_conductance, net.heat_gain))
    n = t.n_nodes
    K = np.zeros((n, n))
    G = np.zeros((n, len(t.input_names)))
    for (i, j), gij in zip(t.links, g):
        K[i, i] += gij
        K[j, j] += gij
        K[i, j] -= gij
        K[j, i] -= gij
    for node, inp, gk in zip(t.boundary_nodes, t.boundary_inputs, gb):
        K[node, node] += gk
        G[node, inp] += gk
    for node, inp, gk in zip(t.heat_nodes, t.heat_inputs, gh):
        G[node, inp] += gk
    return -K / c[:, None], G / c[:, None], K, G


@pytest.mark.slow
@pytest.mark.parametrize("seed, grounded", [(0, True), (3, False)])
def test_random_networks_parallel_paths_match_lsim(seed, grounded):
    """Time constants spread over decades (1e-3..10 J/K, 1e-3..1 W/K); the floating network has
    a zero eigenvalue (no steady state, so x0 is given). Scan and both parallel paths vs lsim."""
    rng = np.random.default_rng(seed)
    net = random_network(rng, 6, grounded=grounded)
    A, B, _, _ = _numpy_matrices(net)
    ts = 0.5 * np.arange(300)
    U = np.stack([20.0 + 10.0 * np.sin(ts / 15.0), 0.01 * (rng.random(ts.size) > 0.5)], axis=1)
    x0 = 20.0 + rng.normal(size=6)
    expected = _lsim_states(A, B, net.topology.input_holds, U, ts, x0)
    for name in ["scan", "parallel-modal", "parallel-dense"]:
        model_of, simulator = EXACT_PATHS[name]
        got = as_np(simulate(model_of(net), U, ts, x0=x0, simulator=simulator).states)
        # Float64 roundoff, amplified by cond(C^1/2) <= 1e2 in the modal path (measured 1.2e-10).
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9, err_msg=name)


# ---------------------------------------------------------------------------------------------
# 5. DiffraxSimulator on linear models (FOH ramp, ZOH staircase, mixed) and a nonlinear one.
# ---------------------------------------------------------------------------------------------

# Global error of Kvaerno5 at rtol = atol = 1e-8 per step, accumulated over the run: measured
# 5.1e-7 K on imu6 (15-60 °C, 300 samples) and 1.4e-7 K on one node; 4x margin. (Before each
# sample interval became its own solve, ZOH inputs gave 8e-6 K: Kvaerno5 evaluates a stage at
# 1.23 steps, past the jump.)
DIFFRAX_ATOL = 2e-6


def test_diffrax_one_node_ramp_matches_analytic():
    """Two uncoupled copies of the one-node network in one `LinearSystem`, the first input
    under FOH and the second under ZOH, both driven by the same ramp."""
    dt = 0.5
    ts = dt * np.arange(161)
    ramp = RAMP["a"] + RAMP["b"] * ts
    system = tj.LinearSystem(A=-np.eye(2) / ONE_TAU, B=np.eye(2) / ONE_TAU, C=np.eye(2),
                             D=np.zeros((2, 2)), holds=("foh", "zoh"))
    sol = simulate(system, np.stack([ramp, ramp], axis=1), ts, x0=np.full(2, RAMP["x0"]),
                   simulator=tj.DiffraxSimulator())
    got = as_np(sol.states)
    np.testing.assert_allclose(got[:, 0], _ramp_foh_exact(ts, tau=ONE_TAU, **RAMP),
                               rtol=0, atol=DIFFRAX_ATOL)
    np.testing.assert_allclose(got[:, 1], _ramp_zoh_exact(ts, tau=ONE_TAU, dt=dt, **RAMP),
                               rtol=0, atol=DIFFRAX_ATOL)
    # The holds differ by ~b dt / 2 = 0.075 K on the steady ramp (4e4 x the tolerance), so the
    # comparison above would catch a simulator that ignored the hold.
    assert got[-1, 0] - got[-1, 1] > 0.07


def test_diffrax_imu6_mixed_holds_matches_exact():
    ts, U, expected = _imu6_reference("lsim")
    net = imu6()
    got = as_np(simulate(net, U, ts, x0=IMU6_X0, simulator=tj.DiffraxSimulator()).states)
    np.testing.assert_allclose(got, expected, rtol=0, atol=DIFFRAX_ATOL)
    # ... and hence agrees with the exact discretization to the same tolerance.
    exact = as_np(simulate(net, U, ts, x0=IMU6_X0).states)
    np.testing.assert_allclose(got, exact, rtol=0, atol=DIFFRAX_ATOL)


@pytest.mark.slow
def test_diffrax_converges_to_exact():
    """Tighter solver tolerances converge onto the exact answer (error ~ tol)."""
    ts, U, expected = _imu6_reference("lsim")
    tight = as_np(simulate(imu6(), U, ts, x0=IMU6_X0,
                           simulator=tj.DiffraxSimulator(rtol=1e-10, atol=1e-10)).states)
    # Measured 7.3e-9 K at rtol = atol = 1e-10; ~4x margin.
    np.testing.assert_allclose(tight, expected, rtol=0, atol=3e-8)


class _RadiatingNode(eqx.Module):
    """One node with convection and radiation to a chamber: `C dT/dt = -G (T - u) - s (T^4 - u^4)`
    (kelvin), a nonlinear model `ExactHold` cannot take."""

    holds: tuple[str, ...] = eqx.field(static=True, default=("foh",))

    def vector_field(self, t, x, u):
        return (-0.5 * (x - u) - 2e-9 * ((x + 273.15) ** 4 - (u + 273.15) ** 4)) / 2.0

    def observe(self, x, u):
        return x

    def steady_state(self, u):
        return u


@pytest.mark.slow
def test_diffrax_nonlinear_matches_radau():
    model = _RadiatingNode()
    ts = 1.0 * np.arange(120)
    U = np.interp(ts, [0, 20, 60, 119], [20.0, 20.0, 100.0, 60.0])[:, None]
    x0 = np.array([150.0])

    def f(t, x, k):
        s = (t - ts[k]) / (ts[k + 1] - ts[k])
        u = U[k] + s * (U[k + 1] - U[k])
        return np.asarray(model.vector_field(t, x, u))

    expected = [x0]
    for k in range(ts.size - 1):
        r = scipy.integrate.solve_ivp(f, (ts[k], ts[k + 1]), expected[-1], args=(k,),
                                      method="Radau", rtol=1e-12, atol=1e-12)
        expected.append(r.y[:, -1])
    got = as_np(simulate(model, U, ts, x0=x0, simulator=tj.DiffraxSimulator()).states)
    np.testing.assert_allclose(got, np.array(expected), rtol=0, atol=DIFFRAX_ATOL)
    with pytest.raises(TypeError, match="linear systems only"):
        tj.simulate(model, U, ts, x0=x0)  # default ExactHold refuses it


# ---------------------------------------------------------------------------------------------
# 6. simulate_batch: different lengths and sample periods.
# ---------------------------------------------------------------------------------------------


def _batch_experiments():
    return [_imu6_profile(n=161, dt=0.5, seed=1), _imu6_profile(n=300, dt=1.0, seed=0),
            _imu6_profile(n=90, dt=2.0, seed=2)]


def test_simulate_batch_matches_separate_runs_and_steady_state():
    net = imu6()
    m = _toml_matrices("imu6.toml")
    experiments = [(U, ts) for ts, U in _batch_experiments()]
    batch = tj.simulate_batch(net, experiments)
    assert len(batch) == len(experiments)
    for (U, ts), sol in zip(experiments, batch):
        assert sol.states.shape == (ts.size, 6) and sol.outputs.shape == (ts.size, 3)
        np.testing.assert_array_equal(as_np(sol.ts), ts)
        # Default x0: the steady state K x = G u[0], solved in NumPy from the TOML values
        # (a 6x6 solve, cond(K) ~ 1e3: roundoff only).
        x_ss = np.linalg.solve(m["K"], m["G"] @ U[0])
        np.testing.assert_allclose(as_np(sol.states[0]), x_ss, rtol=1e-12, atol=0)
        # Same discretization and recurrence, batched by vmap: identical up to roundoff.
        alone = simulate(net, U, ts)
        np.testing.assert_allclose(as_np(sol.states), as_np(alone.states), rtol=1e-12, atol=0)
        np.testing.assert_allclose(as_np(sol.outputs), as_np(alone.outputs), rtol=1e-12, atol=0)
    U, ts = experiments[0]  # dt = 0.5 s, the shortest period
    expected = _lsim_states(m["A"], m["B"], m["holds"], U, ts,
                            np.linalg.solve(m["K"], m["G"] @ U[0]))
    # Exact discretization vs lsim: float64 roundoff (as in test_imu6_mixed_holds_match_scipy).
    np.testing.assert_allclose(as_np(batch[0].states), expected, rtol=1e-9, atol=1e-9)


def test_simulate_batch_explicit_x0():
    net = imu6()
    m = _toml_matrices("imu6.toml")
    experiments = [(U, ts) for ts, U in _batch_experiments()]
    x0s = [IMU6_X0, None, IMU6_X0 + 5.0]
    batch = tj.simulate_batch(net, experiments, x0s=x0s)
    for (U, ts), x0, sol in zip(experiments, x0s, batch):
        start = np.linalg.solve(m["K"], m["G"] @ U[0]) if x0 is None else x0
        # The given x0 is the first row, unchanged; a None entry is the steady state (roundoff).
        np.testing.assert_allclose(as_np(sol.states[0]), start, rtol=1e-12, atol=0)
        expected = _lsim_states(m["A"], m["B"], m["holds"], U, ts, start)
        # Exact discretization vs lsim: float64 roundoff (as in test_imu6_mixed_holds_match_scipy).
        np.testing.assert_allclose(as_np(sol.states), expected, rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# 7. vmap, jit, gradients.
# ---------------------------------------------------------------------------------------------


def test_vmap_matches_loop():
    net = imu6()
    m = _toml_matrices("imu6.toml")
    profiles = [_imu6_profile(seed=s) for s in range(4)]
    ts = profiles[0][0]
    Us = np.stack([U for _, U in profiles])
    x0s = np.stack([IMU6_X0 + s for s in range(4)])
    run = jax.jit(jax.vmap(lambda U, x0: tj.simulate(net, U, ts, x0=x0).states))
    run_ss = jax.jit(jax.vmap(lambda U: tj.simulate(net, U, ts).states))  # default x0 under vmap
    batched, batched_ss = as_np(run(Us, x0s)), as_np(run_ss(Us))
    for i, U in enumerate(Us):
        # Same program per profile, batched: identical up to roundoff.
        np.testing.assert_allclose(batched[i], as_np(simulate(net, U, ts, x0=x0s[i]).states),
                                   rtol=1e-12, atol=0)
        np.testing.assert_allclose(batched_ss[i], as_np(simulate(net, U, ts).states),
                                   rtol=1e-12, atol=0)
    expected = _lsim_states(m["A"], m["B"], m["holds"], Us[2], ts, x0s[2])
    # Exact discretization vs lsim: float64 roundoff (as in test_imu6_mixed_holds_match_scipy).
    np.testing.assert_allclose(batched[2], expected, rtol=1e-9, atol=1e-9)


@pytest.mark.slow  # eager dispatch compiles op by op: slow
def test_jit_matches_eager():
    net = rtd2()
    m = _toml_matrices("rtd2.toml")
    ts = 0.25 * np.arange(80)
    U = np.interp(ts, [0.0, 5.0, 10.0, 20.0], [20.0, 20.0, 80.0, 80.0])[:, None]
    eager = tj.simulate(net, U, ts)
    jitted = jax.jit(lambda net, U: tj.simulate(net, U, ts))(net, U)
    # Same computation, compiled whole or op by op: roundoff only.
    assert eqx.tree_equal(eager, jitted, rtol=1e-13, atol=1e-13)
    x_ss = np.linalg.solve(m["K"], m["G"] @ U[0])
    # Exact discretization vs lsim: float64 roundoff.
    np.testing.assert_allclose(as_np(eager.states), _lsim_states(m["A"], m["B"], m["holds"],
                                                                 U, ts, x_ss),
                               rtol=1e-9, atol=1e-9)


def _central_differences(f, p, h):
    out = np.zeros_like(p)
    for i in range(p.size):
        e = np.zeros_like(p)
        e[i] = h
        out[i] = (float(f(p + e)) - float(f(p - e))) / (2 * h)
    return out


@pytest.mark.parametrize("model, simulator", [
    ("rtd2", tj.ExactHold()),
    pytest.param("rtd2", tj.ExactHold(parallel=True), marks=pytest.mark.slow),  # through eigh
    ("imu6", tj.ExactHold()),
])
def test_gradients_match_finite_differences(model, simulator):
    """d/d(leaves) of a sum-of-squares output loss, through the discretization and (default x0)
    the steady state, against central differences in the unconstrained (log) leaves."""
    net = {"rtd2": rtd2, "imu6": imu6}[model]()
    ts = 1.0 * np.arange(200)
    if model == "rtd2":
        U = np.interp(ts, [0.0, 20.0, 21.0, 120.0, 150.0], [20.0, 20.0, 100.0, 100.0, 60.0])
        U = U[:, None]
    else:
        U = _imu6_profile(n=200)[1]
    target = U[:, :1]  # residual: how far each sensor lags the (first) boundary temperature
    flat, unravel = ravel_pytree(net)

    def loss(p):
        y = tj.simulate(unravel(p), U, ts, simulator=simulator).outputs
        return jnp.sum((y - target) ** 2)

    value_and_grad = jax.jit(jax.value_and_grad(loss))  # one program for both
    value, grad = value_and_grad(flat)
    grad = as_np(grad)
    fd = _central_differences(lambda p: value_and_grad(p)[0], as_np(flat), h=1e-4)
    # Central differences in log leaves: truncation ~h^2 = 1e-8 relative; roundoff of the summed
    # loss (~1e-14 L) / h ~ 1e-10 L, which the absolute floor covers for leaves with almost no
    # influence (the 0.1 s proof mass link: 3e-5 absolute error at h = 1e-4, 3e-4 at h = 1e-5).
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9 * float(value))
    assert np.all(np.isfinite(grad)) and np.abs(grad).max() > 0


# ---------------------------------------------------------------------------------------------
# 8. Error paths.
# ---------------------------------------------------------------------------------------------


def test_simulate_rejects_bad_shapes():
    net = rtd2()
    ts = np.arange(10.0)
    with pytest.raises(ValueError, match="inputs of shape"):
        tj.simulate(net, np.zeros(10), ts)  # inputs 1-d
    with pytest.raises(ValueError, match="inputs of shape"):
        tj.simulate(net, np.zeros((10, 1)), ts[:, None])  # ts 2-d
    with pytest.raises(ValueError, match="inputs of shape"):
        tj.simulate(net, np.zeros((9, 1)), ts)  # lengths differ
    with pytest.raises(ValueError, match="at least two samples"):
        tj.simulate_batch(net, [(np.zeros((1, 1)), np.zeros(1)), (np.zeros((5, 1)), ts[:5])])


def test_exact_hold_rejects_nonlinear_system():
    x0, U, ts = np.array([20.0]), np.full((5, 1), 20.0), np.arange(5.0)
    with pytest.raises(TypeError, match="linear systems only"):
        tj.ExactHold().run(_RadiatingNode(), x0, U, ts)
    with pytest.raises(TypeError, match="linear systems only"):
        tj.simulate(_RadiatingNode(), U, ts, x0=x0, simulator=tj.ExactHold(parallel=True))


def test_diffrax_needs_holds():
    class NoHolds(eqx.Module):
        def vector_field(self, t, x, u):
            return -x

        def observe(self, x, u):
            return x

    with pytest.raises(TypeError, match="holds"):
        tj.simulate(NoHolds(), np.zeros((5, 1)), np.arange(5.0), x0=np.zeros(1),
                    simulator=tj.DiffraxSimulator())


# ---------------------------------------------------------------------------------------------
# 9. The RTD's 90 % rise time (rtd2.toml), from its two poles.
# ---------------------------------------------------------------------------------------------


def _rtd_rise():
    """Unit step response of the core node and its 90 % time, from the eigenvalues.

    The core has no direct input, so its step response starts flat: with decay rates
    `l1 < l2`, `s(t) = 1 - (l2 e^{-l1 t} - l1 e^{-l2 t}) / (l2 - l1)`.
    """
    m = _toml_matrices("rtd2.toml")
    l1, l2 = np.sort(-np.linalg.eigvals(m["A"]).real)

    def s(t):
        return 1.0 - (l2 * np.exp(-l1 * t) - l1 * np.exp(-l2 * t)) / (l2 - l1)

    return m, s, scipy.optimize.brentq(lambda t: s(t) - 0.9, 0.0, 100.0, xtol=1e-14)


def test_rtd_two_pole_formula():
    """The closed form is the core row of x(t) = x_ss + e^{At}(x0 - x_ss) (scipy expm)."""
    m, s, _ = _rtd_rise()
    for t in [0.0, 0.3, 2.0, 7.0, 30.0]:
        x = 1.0 + scipy.linalg.expm(m["A"] * t) @ np.array([-1.0, -1.0])
        assert abs(x[1] - s(t)) < 1e-13  # two evaluations of the same exponential: roundoff


def test_rtd_90_percent_rise_time():
    m, s, t90 = _rtd_rise()
    dt = 0.01
    ts = dt * np.arange(3001)
    # An exact step at t = 0+: start at 20 °C, fluid at 100 °C throughout.
    sol = simulate(rtd2(), np.full((ts.size, 1), 100.0), ts, x0=np.array([20.0, 20.0]))
    y = as_np(sol.outputs)[:, 0]
    # Exact discretization of a constant input: roundoff on ~100 °C over 3000 steps.
    np.testing.assert_allclose(y, 20.0 + 80.0 * s(ts), rtol=0, atol=1e-10)
    y90 = 20.0 + 0.9 * 80.0  # 92 °C
    k = int(np.argmax(y >= y90))
    assert 0.0 <= ts[k] - t90 < dt  # the first sample past 90 % is within one sample
    # A sampled step (20 °C at t = 0, 100 °C from t = dt on): under FOH the input ramps over the
    # first sample, a delay of dt/2; the interpolated 90 % crossing is within one sample.
    u = np.full((ts.size, 1), 100.0)
    u[0] = 20.0
    y = as_np(simulate(rtd2(), u, ts, x0=np.array([20.0, 20.0])).outputs)[:, 0]
    k = int(np.argmax(y >= y90))
    t_cross = ts[k - 1] + dt * (y90 - y[k - 1]) / (y[k] - y[k - 1])
    assert abs(t_cross - t90) < dt
