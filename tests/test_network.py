"""ThermalNetwork, Topology, StableDynamics and the free-parameter vector.

Every number is checked against an independent truth: NumPy/SciPy linear
algebra on matrices built here by hand (or from the TOML file read with
`tomllib`), exact identities of the physics, or finite differences.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import thermojax as tj
from helpers import CONFIGS, as_np, imu6, random_network, toml_network

EPS = np.finfo(np.float64).eps


# Each new topology shape costs a few XLA compilations of the scatter ops (~0.25 s): the
# default run takes two grounded and one ungrounded network per size, `slow` adds more.
def _cases(fast_seeds, slow_seeds):
    return [(seed, n) for n in range(1, 13) for seed in fast_seeds] + \
        [pytest.param(seed, n, marks=pytest.mark.slow) for n in range(1, 13) for seed in slow_seeds]


CASES = _cases(range(2), range(2, 5))
UNGROUNDED = _cases(range(1), range(1, 3))


@functools.lru_cache(maxsize=None)
def _network(seed, n, grounded=True):
    """A random network with its continuous matrices, as NumPy (cached across tests)."""
    net = random_network(np.random.default_rng(seed), n, grounded=grounded)
    sys = net.linear_system()
    return net, as_np(sys.A), as_np(sys.B), as_np(net.capacitance)


def _symmetrized(seed, n, grounded=True):
    """`C^½ A C^-½` from the network's own `A` and capacitances, in NumPy."""
    net, A, _, c = _network(seed, n, grounded)
    s = np.sqrt(c)
    return s[:, None] * A / s[None, :], A


# ---------------------------------------------------------------------------
# Structure of A over many random networks


@pytest.mark.parametrize("seed,n", CASES)
def test_random_network_is_stable(seed, n):
    S, A = _symmetrized(seed, n)
    scale = np.linalg.norm(S, 2)
    # S_ij = -K_ij / sqrt(c_i c_j) up to one rounding per factor: a few ulps of ‖S‖
    np.testing.assert_allclose(S, S.T, rtol=0, atol=8 * EPS * scale)
    lam = np.linalg.eigvalsh(0.5 * (S + S.T))
    # eigvalsh is backward stable (error ~ n eps ‖S‖): demand a margin above that
    assert lam.max() < -100 * n * EPS * scale, lam
    # A = C^-½ S C^½ has the same spectrum: real (imaginary parts are roundoff
    # magnified by the eigenvalue condition, at most cond(C^½) <= 100 here) and negative
    mu = np.linalg.eigvals(A)
    assert np.abs(mu.imag).max() <= 1e-9 * scale, mu
    assert mu.real.max() < 0, mu
    # Similar matrices: the same eigenvalues (relative to ‖S‖: both are backward stable)
    np.testing.assert_allclose(np.sort(mu.real), lam, rtol=0, atol=1e-9 * scale)


@pytest.mark.parametrize("seed,n", UNGROUNDED)
def test_ungrounded_network_has_one_zero_mode(seed, n):
    S, _ = _symmetrized(seed, n, grounded=False)
    scale = max(np.linalg.norm(S, 2), 1e-300)
    np.testing.assert_allclose(S, S.T, rtol=0, atol=8 * EPS * scale)  # a few ulps, as above
    lam = np.linalg.eigvalsh(0.5 * (S + S.T))
    tol = 100 * n * EPS * scale  # backward error of eigvalsh with a safety factor
    assert np.all(lam <= tol), lam
    # The helper builds a connected graph: exactly one zero eigenvalue
    assert np.sum(np.abs(lam) <= tol) == 1, lam
    # ... whose eigenvector is the uniform temperature, C^½ 1 in symmetric coordinates
    s = np.sqrt(_network(seed, n, False)[3])
    np.testing.assert_allclose(S @ s, 0.0, atol=8 * n * EPS * scale * np.linalg.norm(s))  # roundoff


@pytest.mark.parametrize("seed,n", CASES)
def test_uniform_boundary_temperature_is_equilibrium(seed, n):
    """Energy: `T = T_amb 1` with no heat input gives `dT/dt = A 1 + B[:, 0] = 0`."""
    net, A, B, _ = _network(seed, n)
    assert set(net.topology.boundary_inputs) == {0}
    residual = A @ np.ones(n) + B[:, 0]
    # each row is a sum of <= n+1 terms bounded by the row's |A|-sum: n ulps of it
    np.testing.assert_allclose(residual, 0.0, rtol=0,
                               atol=4 * (n + 1) * EPS * np.abs(A).sum(axis=1).max())


@pytest.mark.parametrize("seed,n", [(0, 1), (1, 4), (2, 9), (3, 12)])
def test_matrices_match_hand_built_K(seed, n):
    """`K = L + diag(g_b)` and `A`, `B` built here from the physical values."""
    net = _network(seed, n)[0]
    t = net.topology
    c, g, gb, q = (as_np(x) for x in (net.capacitance, net.conductance,
                                      net.boundary_conductance, net.heat_gain))
    K = np.zeros((n, n))
    for (i, j), gij in zip(t.links, g):
        K[[i, j], [i, j]] += gij
        K[i, j] -= gij
        K[j, i] -= gij
    G = np.zeros((n, len(t.input_names)))
    for node, col, gk in zip(t.boundary_nodes, t.boundary_inputs, gb):
        K[node, node] += gk
        G[node, col] += gk
    for node, col, qk in zip(t.heat_nodes, t.heat_inputs, q):
        G[node, col] += qk
    sys = net.linear_system()
    # sums of at most n+1 positive terms: a few ulps
    np.testing.assert_allclose(as_np(net.conductance_matrix()), K, rtol=1e-14,
                               atol=1e-14 * np.abs(K).max())
    np.testing.assert_allclose(as_np(sys.A), -K / c[:, None], rtol=1e-14,
                               atol=1e-14 * np.abs(K / c[:, None]).max())  # same: one more division
    np.testing.assert_allclose(as_np(sys.B), G / c[:, None], rtol=1e-14)  # one division
    assert np.array_equal(as_np(sys.C)[np.arange(len(t.sensor_nodes)), list(t.sensor_nodes)],
                          np.ones(len(t.sensor_nodes)))
    assert as_np(sys.C).sum() == len(t.sensor_nodes)


# ---------------------------------------------------------------------------
# Construction and validation


def test_from_physical_round_trips():
    topo = random_network(np.random.default_rng(3), 5).topology
    rng = np.random.default_rng(30)
    c = 10 ** rng.uniform(-4, 4, 5)
    g = 10 ** rng.uniform(-4, 4, len(topo.links))
    gb = 10 ** rng.uniform(-4, 4, len(topo.boundary_nodes))
    q = 10 ** rng.uniform(-1, 1, len(topo.heat_nodes))
    net = tj.ThermalNetwork.from_physical(topo, c, g, gb, q)
    # exp(log x): log's rounding (|log x| <= 10 units) times exp's condition, ~ 10 ulp
    for got, want in [(net.capacitance, c), (net.conductance, g),
                      (net.boundary_conductance, gb), (net.heat_gain, q)]:
        np.testing.assert_allclose(as_np(got), want, rtol=1e-14)
    # log's one rounding, |log c| <= 10: 1e-15 absolute
    np.testing.assert_allclose(as_np(net.log_capacitance), np.log(c), rtol=0, atol=1e-15)
    # heat_gain defaults to 1
    net1 = tj.ThermalNetwork.from_physical(topo, c, g, gb)
    assert np.array_equal(as_np(net1.heat_gain), np.ones(len(topo.heat_nodes)))


@pytest.mark.parametrize("bad", [
    dict(capacitance=[1.0, -2.0, 1.0]),
    dict(capacitance=[1.0, 0.0, 1.0]),
    dict(capacitance=[1.0, np.nan, 1.0]),
    dict(capacitance=[[1.0, 1.0, 1.0]]),
    dict(conductance=[0.1, 0.0]),
    dict(conductance=[0.1, -np.inf]),
    dict(boundary_conductance=[-1.0]),
    dict(heat_gain=[0.0]),
])
def test_from_physical_rejects_bad_values(bad):
    topo = tj.Topology(node_names=("a", "b", "c"), links=((0, 1), (1, 2)), boundary_nodes=(0,),
                       boundary_inputs=(0,), heat_nodes=(2,), heat_inputs=(1,),
                       input_names=("T", "P"), input_holds=("foh", "zoh"),
                       sensor_nodes=(2,), sensor_names=("y",))
    values = dict(capacitance=[1.0, 2.0, 3.0], conductance=[0.1, 0.2],
                  boundary_conductance=[0.5], heat_gain=[1.0])
    values.update(bad)
    (what,) = bad
    with pytest.raises(ValueError, match=rf"from_physical\({what}="):
        tj.ThermalNetwork.from_physical(topo, **values)


def _topology(**changes):
    kw = dict(node_names=("a", "b", "c"), links=((0, 1), (1, 2)), boundary_nodes=(0,),
              boundary_inputs=(0,), heat_nodes=(2,), heat_inputs=(1,), input_names=("T", "P"),
              input_holds=("foh", "zoh"), sensor_nodes=(2,), sensor_names=("y",))
    kw.update(changes)
    return tj.Topology(**kw)


@pytest.mark.parametrize("changes,match", [
    (dict(links=((0, 1), (1, 5))), r"\(1, 5\)"),
    (dict(links=((0, 1), (-1, 2))), r"\(-1, 2\)"),
    (dict(links=((0, 1), (1, 1))), r"\(1, 1\)"),
    (dict(boundary_nodes=(7,)), r"node 7"),
    (dict(heat_nodes=(3,)), r"node 3"),
    (dict(sensor_nodes=(-1,)), r"node -1"),
    (dict(heat_inputs=(4,)), r"input 4"),
    (dict(boundary_inputs=(0, 1)), r"mismatched"),
])
def test_topology_rejects_bad_indices(changes, match):
    with pytest.raises(ValueError, match=match):
        _topology(**changes)


def test_network_rejects_wrong_leaf_shapes():
    topo = _topology()
    with pytest.raises(ValueError, match="shapes"):
        tj.ThermalNetwork(jnp.zeros(2), jnp.zeros(2), jnp.zeros(1), jnp.zeros(1), topo)


# ---------------------------------------------------------------------------
# The imu6 model


def test_imu6_matrices_match_toml():
    ref = toml_network(CONFIGS / "imu6.toml")
    net = imu6()
    sys = net.linear_system()
    assert net.topology.input_names == ref["input_names"] == ("T_chamber", "P_asic")
    assert sys.holds == ref["holds"] == ("foh", "zoh")
    # the same few roundings in a different order: 1e-15 of ‖A‖
    np.testing.assert_allclose(as_np(sys.A), ref["A"], rtol=0, atol=1e-15 * np.abs(ref["A"]).max())
    np.testing.assert_allclose(as_np(sys.B), ref["B"], rtol=1e-15)  # one division each


def test_imu6_time_constants():
    ref = toml_network(CONFIGS / "imu6.toml")
    # generalized symmetric eigenproblem K v = lambda C v: no C^-½ needed
    lam = scipy.linalg.eigh(ref["K"], np.diag(ref["c"]), eigvals_only=True)
    tau_ref = np.sort(1.0 / lam)
    tau = as_np(imu6().time_constants())
    assert np.all(np.diff(tau) > 0)
    # eigenvalue error ~ eps ‖C^-½ K C^-½‖ ~ 2e-15 against lambda_min = 3e-3: 1e-12 relative
    np.testing.assert_allclose(tau, tau_ref, rtol=1e-11)
    # the seed's range: enclosure ~300 s, proof mass ~0.1 s
    assert 250 < tau[-1] < 350
    assert 0.05 < tau[0] < 0.2


# ---------------------------------------------------------------------------
# StableDynamics


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("n", [1, 3, 8])
def test_stable_dynamics_is_hurwitz(seed, n):
    rng = np.random.default_rng(seed)
    eps = 10.0 ** rng.uniform(-6, 0)
    M = rng.normal(size=(n, n)) * 10 ** rng.uniform(-3, 1)
    M[:, : n // 2] = 0.0  # rank-deficient M: the bound Re <= -eps is then nearly tight
    S = rng.normal(size=(n, n)) * 10 ** rng.uniform(-3, 2)
    A = as_np(tj.StableDynamics(jnp.asarray(M), jnp.asarray(S), eps=eps).matrix())
    np.testing.assert_allclose(A, -(M @ M.T + eps * np.eye(n)) + (S - S.T), rtol=1e-14,
                               atol=1e-14 * np.abs(A).max())  # one matmul's roundoff
    # Computed eigenvalues are exact for A + E, ‖E‖ ~ n eps_mach ‖A‖, whose numerical range
    # lies in Re <= -eps + ‖E‖; allow 1000 eps_mach ‖A‖ for that backward error.
    slack = 1e3 * EPS * np.linalg.norm(A, 2)
    assert np.linalg.eigvals(A).real.max() <= -eps + slack
    assert np.linalg.eigvalsh(0.5 * (A + A.T)).max() <= -eps + slack


# ---------------------------------------------------------------------------
# Free parameters


def test_free_parameters_round_trip_imu6():
    spec = tj.load_model(CONFIGS / "imu6.toml")
    ref = toml_network(CONFIGS / "imu6.toml")
    net = tj.ThermalNetwork.from_spec(spec)
    mask = tj.parameter_mask(net, spec)
    theta = as_np(tj.free_parameters(net, mask))
    assert theta.shape == (6 + 6 + 1,)  # 6 capacitances, 6 links, 1 boundary; P_asic gain fixed
    links = [0.5, 0.1, 0.02, 0.01, 0.005, 0.03]  # configs/imu6.toml, in file order
    # log of the file's values: one rounding
    np.testing.assert_allclose(theta, np.log(np.r_[ref["c"], links, 0.08]), rtol=0, atol=1e-15)

    new = theta + np.random.default_rng(0).normal(size=theta.shape)
    net2 = tj.with_free_parameters(net, mask, jnp.asarray(new))
    assert np.array_equal(as_np(tj.free_parameters(net2, mask)), new)  # pure gather/scatter
    assert np.array_equal(as_np(net2.log_capacitance), new[:6])
    assert np.array_equal(as_np(net2.log_conductance), new[6:12])
    assert np.array_equal(as_np(net2.log_boundary_conductance), new[12:])
    assert np.array_equal(as_np(net2.log_heat_gain), as_np(net.log_heat_gain))  # the fixed gain
    assert as_np(net2.heat_gain)[0] == 1.0
    assert net2.topology == net.topology

    # it also runs under jit with the mask closed over
    net3 = jax.jit(lambda th: tj.with_free_parameters(net, mask, th))(jnp.asarray(new))
    assert np.array_equal(as_np(net3.log_capacitance), new[:6])

    with pytest.raises(ValueError, match="12 values for 13 free"):
        tj.with_free_parameters(net, mask, jnp.asarray(new[:12]))


# ---------------------------------------------------------------------------
# Differentiability


def test_grad_through_linear_system_matches_finite_differences():
    net = imu6()
    rng = np.random.default_rng(1)
    W = jnp.asarray(rng.normal(size=(6, 6)))
    V = jnp.asarray(rng.normal(size=(6, 6)))

    def f(log_c):
        A = eqx.tree_at(lambda n: n.log_capacitance, net, log_c).linear_system().A
        return jnp.sum(W * A) + 0.5 * jnp.sum(V * (A @ A))

    f_jit = jax.jit(f)
    x0 = net.log_capacitance
    grad = as_np(jax.jit(jax.grad(f))(x0))
    h = 1e-6  # central differences: truncation ~h² and roundoff ~eps/h are both < 1e-9
    fd = np.array([(float(f_jit(x0.at[i].add(h))) - float(f_jit(x0.at[i].add(-h)))) / (2 * h)
                   for i in range(6)])
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())  # FD error
    # and the analytic value for the linear part: dA_ij/dlog c_i = -A_ij
    g_lin = as_np(jax.grad(lambda lc: jnp.sum(W * eqx.tree_at(
        lambda n: n.log_capacitance, net, lc).linear_system().A))(x0))
    A = as_np(net.linear_system().A)
    np.testing.assert_allclose(g_lin, -(as_np(W) * A).sum(axis=1), rtol=1e-13)  # roundoff only
