"""Discretization: exact holds against an mpmath reference, approximations against SciPy.

References, all independent of thermojax:

- `_mp_hold`: the exponential of the augmented matrix `[[A dt, B dt, 0], [0, 0, I],
  [0, 0, 0]]` by `mpmath.expm` at 50 digits (Taylor with scaling and squaring;
  mpmath adds `2j` guard bits for the `j` squarings, so it stays accurate for
  `‖A dt‖ ~ 1e3`). `test_mpmath_reference_is_exact` checks it against the
  closed form through `mpmath.eigsy` of the symmetrized network, which is exact
  for this class.
- `A`, `B` of the model files come from `helpers.toml_network` (the TOML read
  with `tomllib`, `K` assembled by hand), never from thermojax.
- SciPy's `cont2discrete`, `lsim`, `quad_vec`, python-control's `sample_system`,
  and central finite differences for gradients.

Relative errors are measured in the matrix 2-norm: `‖X - X_ref‖₂ / ‖X_ref‖₂`.
"""

import functools

import control
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.signal

import thermojax as tj
from helpers import CONFIGS, as_np, imu6, rtd2, toml_network
from thermojax.dynamics._discretize import _expm, augmented_matrix

DTS = [0.01, 0.1, 1.0, 10.0, 60.0]
MODELS = {"imu6": imu6, "rtd2": rtd2}


def rel(x, ref):
    """Relative error in the matrix 2-norm (vectors: the Euclidean norm)."""
    x, ref = np.asarray(x, dtype=float), np.asarray(ref, dtype=float)
    return np.linalg.norm(x - ref, 2) / np.linalg.norm(ref, 2)


@functools.lru_cache(maxsize=None)
def _toml(name):
    return toml_network(CONFIGS / f"{name}.toml")


@functools.lru_cache(maxsize=None)
def _system(name):
    """thermojax's continuous system of a model file (the code under test)."""
    return MODELS[name]().linear_system()


# ---------------------------------------------------------------------------
# mpmath references


def _to_np(M):
    return np.array([[float(M[i, j]) for j in range(M.cols)] for i in range(M.rows)])


def _augmented(A, B, dt):
    """`[[A dt, B dt, 0], [0, 0, I], [0, 0, 0]]` as an mpmath matrix (A, B are mpmath)."""
    n, m = A.rows, B.cols
    M = mpmath.zeros(n + 2 * m)
    dt = mpmath.mpf(dt)
    for i in range(n):
        for j in range(n):
            M[i, j] = A[i, j] * dt
        for j in range(m):
            M[i, n + j] = B[i, j] * dt
    for j in range(m):
        M[n + j, n + m + j] = 1
    return M


def _blocks(E, n, m, holds):
    """Phi, B0, B1 from the blocks of the augmented exponential (mpmath → float64)."""
    E = _to_np(E)
    E12, E13 = E[:n, n:n + m], E[:n, n + m:]
    foh = np.array([h == "foh" for h in holds])
    B1 = np.where(foh[None, :], E13, 0.0)
    return E[:n, :n], E12 - B1, B1


@functools.lru_cache(maxsize=None)
def _mp_hold(name, dt):
    """Reference Phi, B0, B1 of a model file at `dt`, from float64 `A`, `B` (50 digits)."""
    ref = _toml(name)
    n, m = ref["B"].shape
    with mpmath.workdps(50):
        E = mpmath.expm(_augmented(mpmath.matrix(ref["A"].tolist()),
                                   mpmath.matrix(ref["B"].tolist()), dt))
        return _blocks(E, n, m, ref["holds"])


def _mp_modal(c, K, dps=50):
    """`A = -C⁻¹K = P diag(-lam) Q` exactly: `eigsy` of `C^-½ K C^-½` at `dps` digits."""
    c = [mpmath.mpf(x) for x in c]
    n = len(c)
    S = mpmath.matrix(n)
    for i in range(n):
        for j in range(n):
            S[i, j] = mpmath.mpf(K[i][j]) / mpmath.sqrt(c[i] * c[j])
    lam, V = mpmath.eigsy(S)
    P = mpmath.matrix(n)
    Q = mpmath.matrix(n)
    for i in range(n):
        for k in range(n):
            P[i, k] = V[i, k] / mpmath.sqrt(c[i])
            Q[k, i] = V[i, k] * mpmath.sqrt(c[i])
    return [lam[k] for k in range(n)], P, Q


# ---------------------------------------------------------------------------
# The reference itself


def test_toml_matrices_match_thermojax():
    """The hand-built `A`, `B` are the network's (else the comparisons below are moot)."""
    for name in MODELS:
        ref, sys = _toml(name), _system(name)
        assert sys.holds == ref["holds"]
        # the same roundings in another order: 1e-15 relative
        assert rel(as_np(sys.A), ref["A"]) < 1e-15
        assert rel(as_np(sys.B), ref["B"]) < 1e-15


@pytest.mark.parametrize("dt", [0.01, 60.0])
def test_mpmath_reference_is_exact(dt):
    """`mpmath.expm` of the augmented matrix vs the modal closed form, both at 50 digits.

    Modal: `e^{A t} = P e^{-Λ t} Q`, `E12 = P diag(dt φ1(λ dt)) Q B`, `E13 = P diag(dt φ2) Q B`
    with `φ1(x) = (1 - e^-x)/x`, `φ2(x) = (x - 1 + e^-x)/x²` (the integrals of
    `e^{-λ(dt-s)}` and `e^{-λ(dt-s)} s/dt` over one step).
    """
    ref = _toml("imu6")
    n, m = ref["B"].shape
    with mpmath.workdps(50):
        lam, P, Q = _mp_modal(ref["c"], ref["K"].tolist())
        c = [mpmath.mpf(x) for x in ref["c"]]
        A = P * mpmath.diag([-x for x in lam]) * Q
        B = mpmath.matrix(n, m)
        for i in range(n):
            for j in range(m):
                B[i, j] = mpmath.mpf(ref["G"][i, j]) / c[i]
        E = mpmath.expm(_augmented(A, B, dt))
        t = mpmath.mpf(dt)
        x = [lk * t for lk in lam]
        e = [mpmath.exp(-xk) for xk in x]
        phi1 = [-mpmath.expm1(-xk) / xk for xk in x]
        phi2 = [(xk - 1 + ek) / xk ** 2 for xk, ek in zip(x, e)]
        QB = Q * B
        Phi = P * mpmath.diag(e) * Q
        E12 = P * mpmath.diag([t * p for p in phi1]) * QB
        E13 = P * mpmath.diag([t * p for p in phi2]) * QB
        scale = mpmath.mnorm(E, 1)
        for got, want in [(E[:n, :n], Phi), (E[:n, n:n + m], E12), (E[:n, n + m:], E13)]:
            # both are exact to ~40 of the 50 digits (phi2 loses ~10 to cancellation)
            assert mpmath.mnorm(got - want, 1) < mpmath.mpf(10) ** -35 * scale


# ---------------------------------------------------------------------------
# Exact holds vs the mpmath reference


@pytest.mark.parametrize("method", [tj.MatrixExponential(), tj.Modal()], ids=["expm", "modal"])
@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("name", ["imu6", "rtd2"])
def test_exact_holds_match_mpmath(name, dt, method):
    """imu6 has a ZOH heat input and an FOH boundary temperature: both holds covered."""
    d = tj.discretize(_system(name), dt, method)
    Phi, B0, B1 = _mp_hold(name, dt)
    # float64 roundoff: Padé or eigh plus up to ~10 squarings / products; 1e-14 measured
    for got, want in [(d.Phi, Phi), (d.B0, B0), (d.B1, B1)]:
        assert rel(as_np(got), want) < 1e-12
    # the ZOH column of B1 is exactly zero (P_asic in imu6)
    zoh = np.array([h == "zoh" for h in _toml(name)["holds"]])
    assert np.all(as_np(d.B1)[:, zoh] == 0.0)
    assert float(d.dt) == dt


def test_default_method_is_matrix_exponential():
    sys = _system("imu6")
    a, b = tj.discretize(sys, 1.0), tj.discretize(sys, 1.0, tj.MatrixExponential())
    for x, y in [(a.Phi, b.Phi), (a.B0, b.B0), (a.B1, b.B1)]:
        assert np.array_equal(as_np(x), as_np(y))


def test_naive_taylor_fails_on_stiff_network():
    """The seed's warning: a truncated Taylor series of `A dt` is useless when `‖A dt‖ >> 1`.

    At dt = 60 s, imu6's fastest mode has `λ dt ≈ 640`; the 20-term series of `e^{A dt}`
    sums terms up to `640^20/20! ~ 1e38` that should cancel to `e^-640`.
    """
    A = _toml("imu6")["A"]
    dt = 60.0
    Phi_ref = _mp_hold("imu6", dt)[0]
    term, naive = np.eye(6), np.eye(6)
    for k in range(1, 21):
        term = term @ (A * dt) / k
        naive = naive + term
    assert rel(naive, Phi_ref) > 1.0  # wildly wrong (measured ~1e30)
    assert rel(as_np(tj.discretize(_system("imu6"), dt).Phi), Phi_ref) < 1e-12  # as above


# ---------------------------------------------------------------------------
# One node, analytic


def _one_node(C, g, hold):
    topo = tj.Topology(node_names=("n",), links=(), boundary_nodes=(0,), boundary_inputs=(0,),
                       heat_nodes=(), heat_inputs=(), input_names=("T_amb",), input_holds=(hold,),
                       sensor_nodes=(0,), sensor_names=("T",))
    return tj.ThermalNetwork.from_physical(topo, [C], [], [g]).linear_system()


@pytest.mark.parametrize("method", [tj.MatrixExponential(), tj.Modal()], ids=["expm", "modal"])
@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize("x", [1e-6, 1e-3, 0.1, 1.0, 5.0, 20.0, 100.0])
def test_one_node_analytic(x, hold, method):
    """`C dT/dt = g (u - T)`, `x = g dt / C`: over one step with `u` linear from u0 to u1,

    `T1 = e^-x T0 + ∫0^dt (g/C) e^{-(g/C)(dt-s)} (u0 + (u1-u0) s/dt) ds`
       `= e^-x T0 + (1 - e^-x) u0 + (1 - (1 - e^-x)/x) (u1 - u0)`,
    so FOH: `B1 = 1 - (1 - e^-x)/x`, `B0 = (1 - e^-x)/x - e^-x`; ZOH: `B0 = 1 - e^-x`, `B1 = 0`.
    Evaluated at 40 digits to avoid the cancellation of `1 - e^-x` for small `x`.
    """
    C, g = 2.5, 0.3
    dt = x * C / g
    with mpmath.workdps(40):
        X = mpmath.mpf(g) / mpmath.mpf(C) * mpmath.mpf(dt)
        e = mpmath.exp(-X)
        p = -mpmath.expm1(-X) / X  # (1 - e^-x)/x
        want = (e, p - e, 1 - p) if hold == "foh" else (e, 1 - e, mpmath.mpf(0))
        want = [float(w) for w in want]
    d = tj.discretize(_one_node(C, g, hold), dt, method)
    got = [float(d.Phi[0, 0]), float(d.B0[0, 0]), float(d.B1[0, 0])]
    # e^-x amplifies the rounding of x = (g/C) dt by x: a few ulps times max(1, x)
    np.testing.assert_allclose(got, want, rtol=1e-14 * max(1.0, x), atol=0)


# ---------------------------------------------------------------------------
# Approximations and holds vs SciPy / python-control


@pytest.mark.parametrize("dt", [0.01, 1.0, 60.0])
def test_tustin_matches_scipy_bilinear(dt):
    """SciPy's bilinear form uses the state `ξ = (I - A h) x - h B u`, `h = dt/2`, so
    `Ad = Phi`, `Bd = 2 B0 = 2 B1`, and the outputs agree when `ξ0 = 0`,
    `x0 = (I - A h)⁻¹ h B u0`."""
    ref = _toml("imu6")
    A, B = ref["A"], ref["B"]
    sys = _system("imu6")
    Cy, Dy = as_np(sys.C), as_np(sys.D)
    Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete((A, B, Cy, Dy), dt, method="bilinear")
    d = tj.discretize(sys, dt, tj.Tustin())
    Phi, B0, B1 = as_np(d.Phi), as_np(d.B0), as_np(d.B1)
    # both solve with I - A dt/2 (cond <= 1 + ‖A‖dt/2 ~ 300): 1e-13, with margin
    assert rel(Phi, Ad) < 1e-12
    assert rel(B0, Bd / 2) < 1e-12 and np.array_equal(B0, B1)
    # trajectories: piecewise-linear chamber temperature and a heater switching on/off
    rng = np.random.default_rng(2)
    k = 100
    u = np.c_[20 + np.cumsum(rng.normal(size=k)), (rng.random(k) > 0.5) * 0.2]
    _, y_ref, _ = scipy.signal.dlsim((Ad, Bd, Cd, Dd, dt), u)
    h = dt / 2
    x = np.linalg.solve(np.eye(6) - A * h, h * B @ u[0])
    y = []
    for i in range(k):
        y.append(Cy @ x)
        if i + 1 < k:
            x = Phi @ x + B0 @ u[i] + B1 @ u[i + 1]
    # 100 contracting steps of 1e-13-accurate maps
    np.testing.assert_allclose(np.array(y), y_ref, rtol=1e-10, atol=1e-10 * np.abs(y_ref).max())
    # Tustin keeps the DC gain: its fixed point is the continuous steady state -A⁻¹B u
    ss = np.linalg.solve(np.eye(6) - Phi, (B0 + B1) @ u[-1])
    # cond(I - Phi) ~ 1/(1 - e^-(dt/300)) ≤ 3e4 at dt=0.01, times the 1e-13 above
    np.testing.assert_allclose(ss, np.linalg.solve(A, -B @ u[-1]), rtol=1e-8)


@pytest.mark.parametrize("dt", [0.01, 0.1])
def test_forward_euler_matches_scipy(dt):
    ref = _toml("imu6")
    Ad, Bd, *_ = scipy.signal.cont2discrete((ref["A"], ref["B"], np.eye(6), np.zeros((6, 2))),
                                           dt, method="euler")
    d = tj.discretize(_system("imu6"), dt, tj.ForwardEuler())
    # I + A dt and B dt: one rounding each
    np.testing.assert_allclose(as_np(d.Phi), Ad, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(as_np(d.B0), Bd, rtol=1e-15, atol=0)
    assert np.all(as_np(d.B1) == 0.0)


def test_forward_euler_unstable_beyond_two_tau_min():
    """The documented limit: Euler's `I + A dt` has spectral radius > 1 when dt > 2 τ_min."""
    tau_min = 1.0 / np.linalg.eigvals(-_toml("imu6")["A"]).real.max()
    sys = _system("imu6")

    def rho(dt):
        return np.abs(np.linalg.eigvals(as_np(tj.discretize(sys, dt, tj.ForwardEuler()).Phi))).max()

    assert rho(1.9 * tau_min) < 1.0 < rho(2.1 * tau_min)


@pytest.mark.parametrize("dt", [0.1, 1.0, 60.0])
def test_zoh_matches_scipy_and_control(dt):
    """An all-ZOH imu6: `B0 + B1` is the classical ZOH `Bd` (and `B1 = 0`)."""
    ref = _toml("imu6")
    A, B = ref["A"], ref["B"]
    sys = _system("imu6")
    zsys = tj.LinearSystem(sys.A, sys.B, sys.C, sys.D, holds=("zoh", "zoh"),
                           capacitance=sys.capacitance)
    Cy, Dy = as_np(sys.C), as_np(sys.D)
    Ad, Bd, *_ = scipy.signal.cont2discrete((A, B, Cy, Dy), dt, method="zoh")
    sd = control.sample_system(control.ss(A, B, Cy, Dy), dt, method="zoh")
    for method in [tj.MatrixExponential(), tj.Modal()]:
        d = tj.discretize(zsys, dt, method)
        assert np.all(as_np(d.B1) == 0.0)
        # SciPy's expm is float64 too: both ~1e-14 from the truth (see the mpmath tests)
        for Phi_ref, Bd_ref in [(Ad, Bd), (sd.A, sd.B)]:
            assert rel(as_np(d.Phi), Phi_ref) < 1e-12
            assert rel(as_np(d.Gamma), Bd_ref) < 1e-12


def test_mixed_holds_match_lsim():
    """imu6 with its own holds over 200 samples against `scipy.signal.lsim`.

    `lsim(interp=True)` is exact for piecewise-linear inputs and `interp=False` for
    piecewise-constant ones; by superposition, the FOH chamber temperature and the
    ZOH heater are simulated separately and added (the initial state goes with one).
    """
    ref = _toml("imu6")
    A, B = ref["A"], ref["B"]
    dt, k = 2.0, 200
    ts = dt * np.arange(k)
    rng = np.random.default_rng(5)
    T_ch = 25 + np.cumsum(rng.normal(scale=0.5, size=k))
    P = np.repeat(rng.choice([0.0, 0.15, 0.3], size=k // 10), 10)
    x0 = 25 + rng.normal(size=6)
    eye, zero = np.eye(6), np.zeros((6, 1))
    _, _, x_foh = scipy.signal.lsim((A, B[:, :1], eye, zero), T_ch, ts, X0=x0, interp=True)
    _, _, x_zoh = scipy.signal.lsim((A, B[:, 1:], eye, zero), P, ts, X0=np.zeros(6), interp=False)
    x_ref = x_foh + x_zoh

    d = tj.discretize(_system("imu6"), dt)
    Phi, B0, B1 = as_np(d.Phi), as_np(d.B0), as_np(d.B1)
    u = np.c_[T_ch, P]
    xs = [x0]
    for i in range(k - 1):
        xs.append(Phi @ xs[-1] + B0 @ u[i] + B1 @ u[i + 1])
    # 200 contracting steps, each ~1e-14 relative on both sides
    np.testing.assert_allclose(np.array(xs), x_ref, rtol=1e-9)


# ---------------------------------------------------------------------------
# Process noise (Van Loan)


def _qc():
    """A dense SPD diffusion covariance for imu6 (°C²/s)."""
    rng = np.random.default_rng(0)
    L = rng.normal(size=(6, 6)) * 0.01
    return L @ L.T + np.diag(np.full(6, 1e-4))


@functools.lru_cache(maxsize=None)
def _mp_qd(dt):
    """`Qd = ∫0^dt e^{As} Qc e^{Aᵀs} ds` in closed form at 50 digits.

    With `A = P diag(-λ) Q`: `Qd = P [M_ij (1 - e^{-(λi+λj) dt}) / (λi+λj)] Pᵀ`,
    `M = Q Qc Qᵀ`.
    """
    ref = _toml("imu6")
    with mpmath.workdps(50):
        lam, P, Q = _mp_modal(ref["c"], ref["K"].tolist())
        M = Q * mpmath.matrix(_qc().tolist()) * Q.T
        t = mpmath.mpf(dt)
        n = len(lam)
        W = mpmath.matrix(n)
        for i in range(n):
            for j in range(n):
                s = lam[i] + lam[j]
                W[i, j] = M[i, j] * -mpmath.expm1(-s * t) / s
        return _to_np(P * W * P.T)


@pytest.mark.parametrize("dt", [0.01, 1.0, 60.0])
def test_process_noise_matches_mpmath(dt):
    """Tolerance 1e-10: the mpmath truth uses the exact `C⁻¹K` while thermojax gets the
    float64 `A` (1e-16 relative, amplified by at most `‖A‖dt`-ish conditioning of the
    slow mode ~ O(1)), plus ~log2(‖A‖dt) ≤ 11 doublings each adding roundoff: ~1e-14
    expected, 1e-10 leaves room for other BLAS without hiding a real error (the naive
    Van Loan below is off by 1e255)."""
    A = _toml("imu6")["A"]
    Phi, Qd = tj.discretize_process_noise(jnp.asarray(A), jnp.asarray(_qc()), dt)
    Phi, Qd = as_np(Phi), as_np(Qd)
    Qd_ref = _mp_qd(dt)
    assert rel(Qd, Qd_ref) < 1e-10
    assert rel(Phi, _mp_hold("imu6", dt)[0]) < 1e-10  # same reasoning
    assert np.array_equal(Qd, Qd.T)  # symmetrized by construction
    # positive semidefinite, down to roundoff of its norm
    assert np.linalg.eigvalsh(Qd).min() >= -1e-14 * np.linalg.norm(Qd, 2)


@pytest.mark.parametrize("dt", [0.01, 1.0])
def test_process_noise_matches_quadrature(dt):
    A = _toml("imu6")["A"]
    Qc = _qc()

    def integrand(s):
        E = scipy.linalg.expm(A * s)
        return E @ Qc @ E.T

    Qd_ref, _ = scipy.integrate.quad_vec(integrand, 0.0, dt, epsabs=0, epsrel=1e-14, norm="max")
    _, Qd = tj.discretize_process_noise(jnp.asarray(A), jnp.asarray(Qc), dt)
    # quad_vec to 1e-14 of a smooth integrand: both sides at ~1e-14, same 1e-10 margin
    assert rel(as_np(Qd), Qd_ref) < 1e-10


def test_naive_van_loan_fails_at_dt_60():
    """The unhalved Van Loan block holds `e^{+λ dt}` terms (λ dt ≈ 640) that must cancel.

    Documentation of why `discretize_process_noise` halves the step first."""
    A, Qc = _toml("imu6")["A"], _qc()
    dt, n = 60.0, 6
    M = np.block([[-A, Qc], [np.zeros((n, n)), A.T]]) * dt
    with np.errstate(all="ignore"):
        E = scipy.linalg.expm(M)
        Qd_naive = E[n:, n:].T @ E[:n, n:]
        Qd_ref = _mp_qd(dt)
        err = np.nan_to_num(np.abs(Qd_naive - Qd_ref).max(), nan=np.inf) / np.abs(Qd_ref).max()
    assert err > 1.0  # measured ~1e255 (or non-finite)
    _, Qd = tj.discretize_process_noise(jnp.asarray(A), jnp.asarray(Qc), dt)
    assert rel(as_np(Qd), Qd_ref) < 1e-10  # as in test_process_noise_matches_mpmath


# ---------------------------------------------------------------------------
# Gradients


def _flat(net):
    """The network's array leaves as one vector, and the map back to a network."""
    params, static = eqx.partition(net, eqx.is_array)
    flat, unravel = jax.flatten_util.ravel_pytree(params)
    return flat, lambda th: eqx.combine(unravel(th), static)


def _weights(n, m, seed=0):
    rng = np.random.default_rng(seed)
    return tuple(rng.normal(size=s) for s in [(n, n), (n, m), (n, m)])


@functools.lru_cache(maxsize=None)
def _objective(key, method_cls):
    """`(θ, dt) -> Σ W∘Phi + V∘B0 + U∘B1` over the flat leaves of `NETWORKS[key]()`, with
    fixed random weights; returns `(θ0, jit(f), jit(grad f))`. Cached, and `dt` is an
    argument, so each network and method compiles once for all step sizes."""
    net = NETWORKS[key]()
    flat, rebuild = _flat(net)
    n, m = net.topology.n_nodes, len(net.topology.input_names)
    W, V, U = (jnp.asarray(w) for w in _weights(n, m))

    def f(theta, dt):
        d = tj.discretize(rebuild(theta).linear_system(), dt, method_cls())
        return jnp.sum(W * d.Phi) + jnp.sum(V * d.B0) + jnp.sum(U * d.B1)

    return flat, jax.jit(f), jax.jit(jax.grad(f))


@functools.lru_cache(maxsize=None)
def _central_fd(key, dt, h=1e-6):
    """Central differences of the `MatrixExponential` objective (values ~1e-14 exact, so
    the FD truth does not depend on the method), step `h` on the log-leaves."""
    x, f, _ = _objective(key, tj.MatrixExponential)
    return np.array([(float(f(x.at[i].add(h), dt)) - float(f(x.at[i].add(-h), dt))) / (2 * h)
                     for i in range(x.size)])


@pytest.mark.parametrize("method_cls", [tj.MatrixExponential, tj.Modal], ids=["expm", "modal"])
@pytest.mark.parametrize("dt", [0.1, 1.0, 60.0])
def test_gradients_match_finite_differences(dt, method_cls):
    """All leaves (log capacitance, conductance, boundary conductance, heat gain) of imu6."""
    flat, _, grad = _objective("imu6", method_cls)
    g = as_np(grad(flat, dt))
    fd = _central_fd("imu6", dt)
    # FD error: truncation ~h² ~1e-12, roundoff ~eps |f| / h ~ 1e-10 relative
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    assert np.linalg.norm(g - fd) < 1e-6 * np.linalg.norm(fd)


def _twin_branches(delta, coupling=None):
    """Two identical 2-node branches off one bath, the second's capacitances scaled by
    `1 + delta`, their inner nodes joined by a `coupling` (W/K) link if given."""
    links = ((0, 1), (2, 3)) + (((1, 3),) if coupling is not None else ())
    topo = tj.Topology(node_names=("a1", "b1", "a2", "b2"), links=links,
                       boundary_nodes=(0, 2), boundary_inputs=(0, 0), heat_nodes=(1, 3),
                       heat_inputs=(1, 1), input_names=("T", "P"), input_holds=("foh", "zoh"),
                       sensor_nodes=(1,), sensor_names=("y",))
    c = np.array([1.0, 0.1, 1.0 + delta, 0.1 * (1 + delta)])
    g = [0.05, 0.05] + ([coupling] if coupling is not None else [])
    return tj.ThermalNetwork.from_physical(topo, c, g, [0.2, 0.2], [1.0, 1.0])


NETWORKS = {
    "imu6": imu6,
    # pairs of time constants ~1e-9 apart (relative): perturbation 1e-9, coupling 1e-10 W/K
    "near": lambda: _twin_branches(1e-9, 1e-10),
    # exactly repeated time constants: identical, uncoupled branches
    "repeated": lambda: _twin_branches(0.0),
}


@functools.lru_cache(maxsize=None)
def _mp_objective_grad(key, dt):
    """The exact gradient of `_objective`: central differences at 50 digits on the mpmath
    augmented exponential of `A(θ)`, `B(θ)` (built here from `exp(θ)`), step 1e-15
    (truncation ~1e-30, roundoff ~1e-35)."""
    net = NETWORKS[key]()
    flat, _ = _flat(net)
    t = net.topology
    n, m, nl, nb = t.n_nodes, len(t.input_names), len(t.links), len(t.boundary_nodes)
    W, V, U = _weights(n, m)
    foh = [h == "foh" for h in t.input_holds]

    def f(theta):
        c = [mpmath.exp(v) for v in theta[:n]]
        g = [mpmath.exp(v) for v in theta[n:n + nl]]
        gb = [mpmath.exp(v) for v in theta[n + nl:n + nl + nb]]
        q = [mpmath.exp(v) for v in theta[n + nl + nb:]]
        K, G = mpmath.zeros(n), mpmath.zeros(n, m)
        for (i, j), gk in zip(t.links, g):
            K[i, i] += gk
            K[j, j] += gk
            K[i, j] -= gk
            K[j, i] -= gk
        for node, col, gk in zip(t.boundary_nodes, t.boundary_inputs, gb):
            K[node, node] += gk
            G[node, col] += gk
        for node, col, qk in zip(t.heat_nodes, t.heat_inputs, q):
            G[node, col] += qk
        A, B = mpmath.zeros(n), mpmath.zeros(n, m)
        for i in range(n):
            for j in range(n):
                A[i, j] = -K[i, j] / c[i]
            for j in range(m):
                B[i, j] = G[i, j] / c[i]
        E = mpmath.expm(_augmented(A, B, dt))
        total = mpmath.mpf(0)
        for i in range(n):
            for j in range(n):
                total += W[i, j] * E[i, j]
            for j in range(m):
                e12, e13 = E[i, n + j], E[i, n + m + j]
                b1 = e13 if foh[j] else 0
                total += V[i, j] * (e12 - b1) + U[i, j] * b1
        return total

    grad = []
    with mpmath.workdps(50):
        theta0 = [mpmath.mpf(float(v)) for v in as_np(flat)]
        h = mpmath.mpf(10) ** -15
        for k in range(len(theta0)):
            up, dn = list(theta0), list(theta0)
            up[k] += h
            dn[k] -= h
            grad.append(float((f(up) - f(dn)) / (2 * h)))
    return np.array(grad)


def test_mp_gradient_reference_matches_fd_on_imu6():
    """The 50-digit gradient agrees with float64 FD where both are easy (imu6, dt = 1 s)."""
    # FD error ~1e-10 relative (see test_gradients_match_finite_differences)
    np.testing.assert_allclose(_central_fd("imu6", 1.0), _mp_objective_grad("imu6", 1.0),
                               rtol=1e-6, atol=1e-9 * np.abs(_central_fd("imu6", 1.0)).max())


def _grad_error(key, method_cls, dt):
    flat, _, grad = _objective(key, method_cls)
    exact = _mp_objective_grad(key, dt)
    g = as_np(grad(flat, dt))
    return np.linalg.norm(g - exact) / np.linalg.norm(exact)


@pytest.mark.slow  # compiles gradients for a second network (~5 s)
def test_modal_gradients_degrade_near_coincident_time_constants():
    """Documents the limitation in `_discretize`'s docstring.

    `eigh`'s derivative carries `1/(λi - λj)`; with pairs of eigenvalues ~1e-10 apart
    (relative to ‖S‖ ~ 1) the eigenvectors, and so the modal gradient, are only good
    to ~eps/gap. `MatrixExponential` differentiates the Padé approximant instead and
    stays accurate. Only `MatrixExponential`'s accuracy is asserted as a property; that
    Modal is worse is asserted with a wide margin (measured: 7e-8 vs 2e-16).
    """
    errs = {m.__name__: _grad_error("near", m, 1.0) for m in (tj.MatrixExponential, tj.Modal)}
    # autodiff through Padé + squaring: roundoff only, 2e-16 measured
    assert errs["MatrixExponential"] < 1e-10, errs
    assert errs["Modal"] > 10 * errs["MatrixExponential"], errs


@pytest.mark.slow  # compiles gradients for a third network
def test_expm_gradient_exact_for_repeated_time_constants():
    # roundoff only, as above
    assert _grad_error("repeated", tj.MatrixExponential, 1.0) < 1e-10


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="Modal's gradient goes through eigh, whose derivative "
                   "is 1/(λi-λj): NaN or garbage for exactly repeated time constants (identical "
                   "branches). Known limitation; use MatrixExponential for gradients.")
def test_modal_gradient_exact_for_repeated_time_constants():
    assert _grad_error("repeated", tj.Modal, 1.0) < 1e-6  # what a fix would have to reach


def _expm_cases():
    """Random matrices needing no squaring to several squarings (the largest Hurwitz,
    `-(R Rᵀ) + (S - Sᵀ)`, so that `e^M` is well conditioned), and the stiff augmented
    matrices of imu6 (time constants 0.1 s to ~300 s) at dt = 0.01 s and 60 s."""
    rng = np.random.default_rng(4)
    cases = [rng.standard_normal((8, 8)) * scale for scale in (1e-3, 0.3, 2.0)]
    R, S = 3.0 * rng.standard_normal((2, 8, 8))
    cases.append(-(R @ R.T) + (S - S.T))
    sys = _system("imu6")
    for dt in (0.01, 60.0):
        cases.append(np.asarray(augmented_matrix(sys, jnp.asarray(dt))))
    return cases


def test_expm_and_its_derivatives_match_scipy():
    """The exponential of `MatrixExponential` and its written-out derivative against
    `scipy.linalg.expm` / `expm_frechet`: forward mode (`jax.jvp`), reverse mode
    (`jax.vjp`, the transposed rule: `<G, L(dM)> = <L*(G), dM>`) and both under
    `jax.vmap` (where the squarings of a batch run masked)."""
    rng = np.random.default_rng(5)
    Ms = _expm_cases()
    dMs = [rng.standard_normal(M.shape) for M in Ms]
    Gs = [rng.standard_normal(M.shape) for M in Ms]
    jvp = jax.jit(lambda M, dM: jax.jvp(_expm, (M,), (dM,)))
    vjp = jax.jit(lambda M, G: jax.vjp(_expm, M)[1](G)[0])
    for M, dM, G in zip(Ms, dMs, Gs):
        E_ref, dE_ref = scipy.linalg.expm_frechet(M, dM)
        E, dE = jvp(M, dM)
        # roundoff of scaling and squaring (both sides): 2e-16 to 2e-14 measured, ‖M‖₁ <= 750
        assert rel(E, E_ref) < 1e-13
        assert rel(dE, dE_ref) < 1e-12
        adjoint = np.sum(as_np(vjp(M, G)) * dM)  # <L*(G), dM>
        assert abs(adjoint - np.sum(G * dE_ref)) < 1e-12 * np.linalg.norm(G) * np.linalg.norm(
            dE_ref)  # a transposed linear map: roundoff only
    # The same under vmap (8 x 8 cases only: one batch).
    M8 = jnp.asarray(np.stack(Ms[:4]))
    dM8 = jnp.asarray(np.stack(dMs[:4]))
    E, dE = jax.jit(jax.vmap(lambda M, dM: jax.jvp(_expm, (M,), (dM,))))(M8, dM8)
    G8 = jnp.asarray(np.stack(Gs[:4]))
    cot = jax.jit(jax.vmap(lambda M, G: jax.vjp(_expm, M)[1](G)[0]))(M8, G8)
    for k in range(4):
        E_ref, dE_ref = scipy.linalg.expm_frechet(Ms[k], dMs[k])
        assert rel(E[k], E_ref) < 1e-13 and rel(dE[k], dE_ref) < 1e-12  # roundoff, as above
        assert abs(np.sum(as_np(cot[k]) * dMs[k]) - np.sum(Gs[k] * dE_ref)) < \
            1e-12 * np.linalg.norm(Gs[k]) * np.linalg.norm(dE_ref)


def test_expm_jacrev_equals_jacfwd():
    """Reverse and forward Jacobians of the exponential of a small stiff matrix agree."""
    M = jnp.asarray(_expm_cases()[-1])
    Jf = jax.jit(jax.jacfwd(_expm))(M)
    Jr = jax.jit(jax.jacrev(_expm))(M)
    # both exact derivatives of the same approximant: roundoff only
    np.testing.assert_allclose(Jr, Jf, rtol=0, atol=1e-13 * float(jnp.max(jnp.abs(Jf))))


# ---------------------------------------------------------------------------
# Transformations


@pytest.mark.parametrize("method", [tj.MatrixExponential(), tj.Modal()], ids=["expm", "modal"])
def test_jit_vmap_over_dt(method):
    sys = _system("imu6")
    dts = jnp.array([0.01, 0.5, 3.0, 60.0])
    batched = jax.jit(jax.vmap(lambda dt: tj.discretize(sys, dt, method)))(dts)
    assert batched.Phi.shape == (4, 6, 6) and batched.B0.shape == (4, 6, 2)
    for k, dt in enumerate(dts):
        one = tj.discretize(sys, float(dt), method)
        for a, b in [(batched.Phi[k], one.Phi), (batched.B0[k], one.B0), (batched.B1[k], one.B1)]:
            # the same algorithm batched: equal up to roundoff of the fused/batched kernels
            np.testing.assert_allclose(as_np(a), as_np(b), rtol=1e-13, atol=1e-15)
    # and every batched step is still exact (vs mpmath, as above)
    for k, dt in enumerate([0.01, 60.0]):
        idx = [0, 3][k]
        assert rel(as_np(batched.Phi[idx]), _mp_hold("imu6", dt)[0]) < 1e-12


def test_modal_needs_capacitance():
    sys = _system("imu6")
    general = tj.LinearSystem(sys.A, sys.B, sys.C, sys.D, holds=sys.holds)
    with pytest.raises(TypeError, match="MatrixExponential"):
        tj.discretize(general, 1.0, tj.Modal())
