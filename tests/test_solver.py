"""The truncated Gauss-Newton solver (`thermojax.fitting._solver.gauss_newton`) on small problems.

Truths, independent of the code under test: `scipy.optimize.least_squares` (MINPACK's
Levenberg-Marquardt) on the same residuals written in NumPy, a Jacobian written out by
hand, and the closed-form least-squares solution of a problem with one direction the
data cannot determine.
"""

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from thermojax.fitting._solver import TruncatedGaussNewton, gauss_newton

T1 = np.linspace(0.0, 5.0, 40)
T2 = np.linspace(0.0, 3.0, 25)


def _decay(theta, t):
    """`exp(la) exp(-exp(lb) t) + c`."""
    la, lb, c = theta
    return jnp.exp(la) * jnp.exp(-jnp.exp(lb) * t) + c


def _data():
    rng = np.random.default_rng(0)
    truth = np.array([np.log(2.0), np.log(0.7), 0.3])
    y1 = np.asarray(_decay(truth, T1)) + 0.01 * rng.standard_normal(T1.shape)
    # The second data set: 5 x 5 grid of samples, to exercise a 2-D residual leaf.
    y2 = np.asarray(_decay(truth, T2)) + 0.02 * rng.standard_normal(T2.shape)
    return y1, y2.reshape(5, 5)


def _residuals(theta, data):
    """A pytree of residuals: a vector and a 5 x 5 array, weighted differently."""
    y1, y2 = data
    return ((y1 - _decay(theta, T1)) / 0.01,
            (y2 - _decay(theta, T2).reshape(5, 5)) / 0.02)


def _numpy_jacobian(theta):
    """d residuals / d theta, written out by hand: (40 + 25, 3)."""
    la, lb, _ = theta

    def one(t, w):
        e = np.exp(-np.exp(lb) * t)
        return -np.stack([np.exp(la) * e, -np.exp(la) * e * np.exp(lb) * t,
                          np.ones_like(t)], axis=1) / w

    return one(T1, 0.01), one(T2, 0.02)


def _scipy_reference(data):
    """`scipy.optimize.least_squares` (MINPACK LM, the Jacobian by hand) on `_residuals`."""
    def flat(theta):
        r1, r2 = _residuals(jnp.asarray(theta), data)
        return np.concatenate([np.asarray(r1), np.asarray(r2).ravel()])

    return scipy.optimize.least_squares(flat, np.zeros(3), method="lm",
                                        jac=lambda th: np.concatenate(_numpy_jacobian(th)),
                                        xtol=1e-15, ftol=1e-15, gtol=1e-15)


def test_pytree_residuals_match_scipy_least_squares():
    data = _data()
    theta0 = jnp.array([0.0, 0.0, 0.0])
    # ½χ² is about 26 here, its rounding 6e-15: a last step that would lower it by 1e-17
    # is taken or not by the XLA build (jaxlib 0.10.2 under the suite's XLA flags: not),
    # so tol 1e-20 failed by rounding, and the point agrees with SciPy to 1.4e-10 (taken:
    # 7e-12). tol 1e-14 and rtol 1e-9 (√eps over the curvature's scale) hold for both.
    sol = jax.jit(lambda t0, d: gauss_newton(_residuals, t0, d, TruncatedGaussNewton(
        min_singular_value=1e-6, tol=1e-14)))(theta0, data)
    assert bool(sol.converged) and int(sol.num_truncated) == 0

    ref = _scipy_reference(data)
    np.testing.assert_allclose(sol.value, ref.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(float(sol.cost), 0.5 * np.sum(ref.fun ** 2), rtol=1e-12)
    # One Gram matrix per residual leaf, at the solution.
    J1, J2 = _numpy_jacobian(np.asarray(sol.value))
    np.testing.assert_allclose(sol.grams[0], J1.T @ J1, rtol=1e-10)
    np.testing.assert_allclose(sol.grams[1], J2.T @ J2, rtol=1e-10)
    assert sol.residuals[1].shape == (5, 5)


def test_undetermined_direction_stays_where_it_started():
    """`y = exp(la + lb) t`: only `la + lb` is determined. The solver fits it exactly
    (closed form) and leaves `la - lb` at its starting value."""
    rng = np.random.default_rng(1)
    t = np.linspace(0.1, 2.0, 30)
    y = 3.0 * t + 0.05 * rng.standard_normal(t.shape)

    def residuals(theta, y):
        return (y - jnp.exp(theta[0] + theta[1]) * t) / 0.05

    theta0 = jnp.array([0.4, -0.9])
    solver = TruncatedGaussNewton(tol=1e-20)
    sol = jax.jit(lambda t0, y: gauss_newton(residuals, t0, y, solver))(theta0, jnp.asarray(y))
    slope = np.sum(t * y) / np.sum(t * t)  # least squares through the origin
    assert bool(sol.converged) and int(sol.num_truncated) == 1
    np.testing.assert_allclose(float(sol.value[0] + sol.value[1]), np.log(slope), rtol=0,
                               atol=1e-10)
    np.testing.assert_allclose(float(sol.value[0] - sol.value[1]), 0.4 - (-0.9), rtol=0,
                               atol=1e-12)


def test_reweight_maximizes_the_likelihood_profiled_over_each_leafs_noise():
    """With `reweight` giving each residual leaf the weight `sqrt(N_k / Σ r_k²)` at the
    current point, one solve maximizes the Gaussian likelihood with each leaf's noise
    std at its ML value, `-Σ_k (N_k/2) log Σ r_k²` (up to constants). Truth: SciPy's
    BFGS on that profiled objective written in NumPy. The data's two noise levels differ
    five-fold, and the solve starts with both weighted alike (unit weights)."""
    rng = np.random.default_rng(2)
    truth = np.array([np.log(2.0), np.log(0.7), 0.3])
    y1 = np.asarray(_decay(truth, T1)) + 0.01 * rng.standard_normal(T1.shape)
    y2 = np.asarray(_decay(truth, T2)) + 0.05 * rng.standard_normal(T2.shape)
    data = (jnp.asarray(y1), jnp.asarray(y2))

    def residuals(theta, data):
        return (data[0] - _decay(theta, T1), data[1] - _decay(theta, T2))

    def reweight(r):
        return tuple(jnp.sqrt(x.size / jnp.sum(x ** 2)) for x in r)

    sol = jax.jit(lambda t0, d: gauss_newton(residuals, t0, d, TruncatedGaussNewton(
        min_singular_value=1e-6, tol=1e-14), reweight=reweight))(jnp.zeros(3), data)
    assert bool(sol.converged)

    def profiled(theta):
        la, lb, c = theta
        s1 = np.sum((y1 - (np.exp(la) * np.exp(-np.exp(lb) * T1) + c)) ** 2)
        s2 = np.sum((y2 - (np.exp(la) * np.exp(-np.exp(lb) * T2) + c)) ** 2)
        return 0.5 * T1.size * np.log(s1) + 0.5 * T2.size * np.log(s2)

    ref = scipy.optimize.minimize(profiled, np.zeros(3), method="BFGS",
                                  options={"gtol": 1e-10, "xrtol": 1e-14})
    np.testing.assert_allclose(sol.value, ref.x, rtol=0, atol=1e-6)
    assert profiled(np.asarray(sol.value)) <= ref.fun + 1e-9
    # The last weights are the ML noise stds' inverses at the solution.
    r1, r2 = (np.asarray(x) for x in residuals(sol.value, data))
    np.testing.assert_allclose([float(w) for w in sol.weights],
                               [np.sqrt(r1.size / np.sum(r1 ** 2)),
                                np.sqrt(r2.size / np.sum(r2 ** 2))], rtol=1e-12)
    np.testing.assert_allclose(1.0 / np.asarray(sol.weights), [0.01, 0.05], rtol=0.3)
    # Residuals and grams come back weighted: each leaf's Σ (w r)² is its sample count.
    np.testing.assert_allclose([float(np.sum(np.asarray(x) ** 2)) for x in sol.residuals],
                               [T1.size, T2.size], rtol=1e-12)


def test_hinted_jacobian_gets_the_hint_of_its_own_point():
    """With `hinted`, `fn` returns `(residuals, hint)` and `jac` gets the hint of the
    point it linearizes at. Here the hint is the point itself and `jac` linearizes at
    the hint, not at its `theta`: a stale hint (another trial's, or the previous
    iterate's) would linearize in the wrong place and land elsewhere than SciPy."""
    data = _data()

    def fn(theta, data):
        return _residuals(theta, data), theta

    def jac(theta, data, hint):
        J, r = jax.jacfwd(lambda t: (_residuals(t, data),) * 2, has_aux=True)(hint)
        return r, J, None

    sol = jax.jit(lambda t0, d: gauss_newton(fn, t0, d, TruncatedGaussNewton(
        min_singular_value=1e-6, tol=1e-14), jac=jac, hinted=True))(jnp.zeros(3), data)
    plain = jax.jit(lambda t0, d: gauss_newton(_residuals, t0, d, TruncatedGaussNewton(
        min_singular_value=1e-6, tol=1e-14)))(jnp.zeros(3), data)
    assert bool(sol.converged)
    # two programs: the same steps to rounding (XLA may fuse them differently); a stale
    # hint would land elsewhere, far beyond this
    np.testing.assert_allclose(np.asarray(sol.value), np.asarray(plain.value), rtol=1e-12)
    assert int(sol.num_steps) == int(plain.num_steps)

    ref = _scipy_reference(data)
    np.testing.assert_allclose(sol.value, ref.x, rtol=1e-9, atol=1e-12)
