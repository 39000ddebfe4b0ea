"""Discretization of a continuous linear system, exact or approximate, differentiable.

Which method when (float64):

- `MatrixExponential` (default): Padé scaling-and-squaring of an augmented
  matrix, exact for both holds, any system. Accurate to ~1e-14 relative on stiff
  thermal networks (0.1 s to 300 s time constants, dt from 0.01 s to 60 s), with
  gradients through the written-out derivative of the Padé approximant (forward
  and reverse mode): safe everywhere.
- `Modal`: closed form through the eigendecomposition of the symmetrized network
  (`LinearSystem.capacitance` must be set). Values as accurate as
  `MatrixExponential`; its gradients go through `eigh`, whose derivative has
  `1/(λ_i - λ_j)` terms, so they lose accuracy when two coupled time constants
  nearly coincide (7e-8 relative at a 1e-9 split, against 2e-16 for
  `MatrixExponential`) and are NaN when two are exactly equal (two identical
  branches). Use it for values (and the diagonal associative scan), not for
  gradients.
- `Tustin`, `ForwardEuler`: approximations for comparison only. Euler is
  unstable for `dt > 2 τ_min`.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..model._system import DiscreteSystem, LinearSystem


class AbstractDiscretization(eqx.Module):
    """Turns a `LinearSystem` and a sample period into a `DiscreteSystem`."""

    @abc.abstractmethod
    def discretize(self, system: LinearSystem, dt) -> DiscreteSystem:
        ...


def discretize(system: LinearSystem, dt, method: AbstractDiscretization | None = None
               ) -> DiscreteSystem:
    """Sample `system` with period `dt` (s).

    **Arguments:**

    - `system`: the continuous `LinearSystem`; its `holds` say, per input,
      whether the input is piecewise linear (`"foh"`) or constant (`"zoh"`)
      between samples.
    - `dt`: sample period in seconds, a positive scalar.
    - `method`: an `AbstractDiscretization`; default `MatrixExponential()`.

    **Returns:** a `DiscreteSystem` with `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]`.
    """
    method = MatrixExponential() if method is None else method
    return method.discretize(system, jnp.asarray(dt, dtype=system.A.dtype))


_THETA13 = 5.371920351148152  # Higham (2005): Padé [13/13] is accurate for ‖M‖₁ <= θ13
_MAX_SQUARINGS = 64
# Padé [13/13] coefficients (Higham 2005), as in `jax.scipy.linalg.expm`.
_B13 = (64764752532480000., 32382376266240000., 7771770303897600., 1187353796428800.,
        129060195264000., 10559470521600., 670442572800., 33522128640., 1323241920.,
        40840800., 960960., 16380., 182., 1.)


def _solve_small(A: Float[Array, "n n"], B: Float[Array, "n k"]) -> Float[Array, "n k"]:
    """`A⁻¹ B` by Gauss-Jordan elimination with partial pivoting (`A` small, `n` static).

    Plain array operations in a short loop instead of LAPACK: on CPU, JAX calls LAPACK
    through SciPy's OpenBLAS, whose triangular solves start worker threads even for
    10 x 10 systems and leave them spinning; inside a fit loop on a busy machine they
    take the cores from XLA.
    """
    n = A.shape[0]
    rows = jnp.arange(n)

    def eliminate(i, M):
        col = jax.lax.dynamic_index_in_dim(M, i, axis=1, keepdims=False)
        piv = jnp.argmax(jnp.where(rows >= i, jnp.abs(col), -1.0))
        M = M[jnp.where(rows == i, piv, jnp.where(rows == piv, i, rows))]  # swap rows i, piv
        pivot_row = jax.lax.dynamic_index_in_dim(M, i, axis=0, keepdims=False)
        pivot_row = pivot_row / jax.lax.dynamic_index_in_dim(pivot_row, i, keepdims=False)
        col = jax.lax.dynamic_index_in_dim(M, i, axis=1, keepdims=False)
        M = M - jnp.where(rows == i, 0.0, col)[:, None] * pivot_row[None, :]
        return jnp.where((rows == i)[:, None], pivot_row[None, :], M)

    return jax.lax.fori_loop(0, n, eliminate, jnp.concatenate([A, B], axis=1))[:, n:]


def _squarings(M):
    """The number `s` of squarings (a float in `[0, 64]`, no gradient) of the scaling
    `‖M‖₁ / 2^s <= θ13` (Higham 2005). JAX's own `expm` uses `floor` where the algorithm
    needs `ceil`, so it applies the approximant up to `2 θ13` (`e^-10` 2e-8 off)."""
    norm = jax.lax.stop_gradient(jnp.linalg.norm(M, 1))
    return jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / _THETA13)), 0, _MAX_SQUARINGS)


def _pade13(A, dA=None):
    """`(U, V)` of the Padé [13/13] approximant `e^A ≈ (V - U)⁻¹ (V + U)`, and with `dA`
    their derivatives `(dU, dV)` along it (product rule: linear in `dA`)."""
    b = _B13
    ident = jnp.eye(A.shape[0], dtype=A.dtype)
    A2 = A @ A
    A4 = A2 @ A2
    A6 = A4 @ A2
    W1 = b[13] * A6 + b[11] * A4 + b[9] * A2
    inner = A6 @ W1 + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * ident
    U = A @ inner
    W2 = b[12] * A6 + b[10] * A4 + b[8] * A2
    V = A6 @ W2 + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * ident
    if dA is None:
        return U, V
    dA2 = dA @ A + A @ dA
    dA4 = dA2 @ A2 + A2 @ dA2
    dA6 = dA4 @ A2 + A4 @ dA2
    dW1 = b[13] * dA6 + b[11] * dA4 + b[9] * dA2
    dinner = dA6 @ W1 + A6 @ dW1 + b[7] * dA6 + b[5] * dA4 + b[3] * dA2
    dU = dA @ inner + A @ dinner
    dW2 = b[12] * dA6 + b[10] * dA4 + b[8] * dA2
    dV = dA6 @ W2 + A6 @ dW2 + b[6] * dA6 + b[4] * dA4 + b[2] * dA2
    return U, V, dU, dV


@jax.custom_jvp
def _expm(M: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """`e^M` by scaling and squaring (Higham 2005): Padé [13/13] of `M / 2^s` with
    `‖M‖₁ / 2^s <= θ13`, then `s` squarings. Accurate to ~1e-15 relative on stiff
    networks; `_squarings` says why not `jax.scipy.linalg.expm`.

    Its derivative (`_expm_jvp`) is written out, linear in the tangent, so both
    `jax.jvp` (the fit's Jacobians: a few small products per tangent) and `jax.grad`
    (its transpose) work.
    """
    s = _squarings(M)
    U, V = _pade13(M * 2.0 ** (-s))
    E = _solve_small(V - U, V + U)
    return jax.lax.fori_loop(0, s.astype(int), lambda i, E: E @ E, E)


@_expm.defjvp
def _expm_jvp(primals, tangents):
    """`d e^M` along `dM`: the Padé terms differentiated,
    `dE = (V - U)⁻¹ (dV + dU - (dV - dU) E)`, then `dE ← dE E + E dE` at each squaring.

    Every tangent operation is a product with a primal matrix, so JAX can transpose it
    (`jax.grad`). The squarings are a scan of fixed length `_MAX_SQUARINGS`, whose steps
    past `s` are skipped by `lax.cond`; under `jax.vmap` over matrices (`s` batched) they
    are masked instead and all run, so the fit maps its runs' exponentials with `lax.map`.
    """
    (M,), (dM,) = primals, tangents
    n = M.shape[0]
    s = _squarings(M)
    scale = 2.0 ** (-s)
    U, V, dU, dV = _pade13(M * scale, dM * scale)
    EW = _solve_small(V - U, jnp.concatenate([V + U, jnp.eye(n, dtype=M.dtype)], axis=1))
    E, W_inv = EW[:, :n], EW[:, n:]  # e^(M/2^s), (V - U)⁻¹
    dE = W_inv @ ((dV + dU) - (dV - dU) @ E)

    def square(carry, i):
        return jax.lax.cond(i < s, lambda c: (c[0] @ c[0], c[1] @ c[0] + c[0] @ c[1]),
                            lambda c: c, carry), None

    return jax.lax.scan(square, (E, dE), jnp.arange(_MAX_SQUARINGS))[0]


def _split_holds(system: LinearSystem, E12, E13):
    """B0, B1 from the step integrals: `E12 u[k] + E13 (u[k+1] - u[k])` for FOH inputs."""
    foh = jnp.array([h == "foh" for h in system.holds], dtype=E12.dtype)
    B1 = E13 * foh[None, :]
    return E12 - B1, B1


class MatrixExponential(AbstractDiscretization):
    """Exact ZOH/FOH via `expm` of `[[A dt, B dt, 0], [0, 0, I], [0, 0, 0]]`.

    With the input `u(t) = u[k] + (t/dt)(u[k+1] - u[k])`, the state after one
    step is `E11 x + E12 u[k] + E13 (u[k+1] - u[k])`, read off the blocks of the
    exponential. Zero-order-hold inputs drop the `E13` term.
    """

    def discretize(self, system: LinearSystem, dt) -> DiscreteSystem:
        return discrete_from_exponential(system, dt, _expm(augmented_matrix(system, dt)))


def augmented_matrix(system: LinearSystem, dt) -> Float[Array, "k k"]:
    """`[[A dt, B dt, 0], [0, 0, I], [0, 0, 0]]`, whose exponential holds the exact
    one-step maps for inputs that vary linearly over the step."""
    n, m = system.B.shape
    M = jnp.zeros((n + 2 * m, n + 2 * m), dtype=system.A.dtype)
    M = M.at[:n, :n].set(system.A * dt).at[:n, n:n + m].set(system.B * dt)
    return M.at[n:n + m, n + m:].set(jnp.eye(m, dtype=system.A.dtype))


def discrete_from_exponential(system: LinearSystem, dt, E) -> DiscreteSystem:
    """The `DiscreteSystem` read off the blocks of `expm(augmented_matrix(system, dt))`."""
    n, m = system.B.shape
    B0, B1 = _split_holds(system, E[:n, n:n + m], E[:n, n + m:])
    return DiscreteSystem(E[:n, :n], B0, B1, system.C, system.D, dt)


def _phi1(x):
    """`(1 - e^-x)/x`, stable for all x >= 0."""
    small = x < 1e-8
    xs = jnp.where(small, 1.0, x)
    return jnp.where(small, 1.0 - 0.5 * x, -jnp.expm1(-xs) / xs)


def _phi2(x):
    """`(x - 1 + e^-x)/x²` = ∫0^1 s e^{-x(1-s)} ds, stable for all x >= 0."""
    small = x < 0.1
    xs = jnp.where(small, 1.0, x)
    series = jnp.zeros_like(x)
    fact = 2.0
    for k in range(12):  # Σ (-x)^k/(k+2)!, truncation < 1e-19 for x < 0.1
        series = series + (-x) ** k / fact
        fact *= k + 3
    return jnp.where(small, series, (xs + jnp.expm1(-xs)) / xs ** 2)


def modal_decomposition(system: LinearSystem):
    """`A = P diag(-lam) Q` with `Q P = I`, from the symmetric form of a thermal network.

    Returns `(lam, P, Q)`: decay rates `lam >= 0` (1/s), and the modal bases.
    Needs `system.capacitance`.
    """
    if system.capacitance is None:
        raise TypeError("`Modal` discretization needs a reciprocal thermal network "
                        "(`LinearSystem.capacitance` set, as `ThermalNetwork.linear_system()` "
                        "does). Use `MatrixExponential()` for a general system.")
    s = jnp.sqrt(system.capacitance)
    S = -(s[:, None] * system.A) / s[None, :]
    lam, V = jnp.linalg.eigh(0.5 * (S + S.T))
    return lam, V / s[:, None], V.T * s[None, :]


class Modal(AbstractDiscretization):
    """Closed-form exact ZOH/FOH for a reciprocal network, through `eigh`.

    `A = -C⁻¹K` is similar to `S = C^-½ K C^-½ = V Λ Vᵀ`, so
    `e^{A dt} = C^-½ V e^{-Λ dt} Vᵀ C^½` and the hold integrals are the scalar
    functions `dt (1-e^-x)/x` and `dt (x-1+e^-x)/x²` of `x = λ dt`, each
    evaluated without cancellation. See the module docstring on gradients.
    """

    def discretize(self, system: LinearSystem, dt) -> DiscreteSystem:
        lam, P, Q = modal_decomposition(system)
        x = lam * dt
        QB = Q @ system.B
        Phi = (P * jnp.exp(-x)[None, :]) @ Q
        E12 = (P * (dt * _phi1(x))[None, :]) @ QB
        E13 = (P * (dt * _phi2(x))[None, :]) @ QB
        B0, B1 = _split_holds(system, E12, E13)
        return DiscreteSystem(Phi, B0, B1, system.C, system.D, dt)


class Tustin(AbstractDiscretization):
    """Bilinear (trapezoidal) approximation: `(I - A dt/2) x[k+1] = (I + A dt/2) x[k] + B dt/2 (u[k] + u[k+1])`."""

    def discretize(self, system: LinearSystem, dt) -> DiscreteSystem:
        n = system.n_states
        Minus = jnp.eye(n) - 0.5 * dt * system.A
        Phi = jnp.linalg.solve(Minus, jnp.eye(n) + 0.5 * dt * system.A)
        Bh = jnp.linalg.solve(Minus, 0.5 * dt * system.B)
        return DiscreteSystem(Phi, Bh, Bh, system.C, system.D, dt)


class ForwardEuler(AbstractDiscretization):
    """Explicit Euler `x[k+1] = (I + A dt) x[k] + B dt u[k]`: unstable if dt > 2 τ_min."""

    def discretize(self, system: LinearSystem, dt) -> DiscreteSystem:
        n = system.n_states
        return DiscreteSystem(jnp.eye(n) + dt * system.A, dt * system.B,
                              jnp.zeros_like(system.B), system.C, system.D, dt)


_MAX_HALVINGS = 64


def discretize_process_noise(A: Float[Array, "n n"], Qc: Float[Array, "n n"], dt
                             ) -> tuple[Float[Array, "n n"], Float[Array, "n n"]]:
    """Van Loan: `Phi = e^{A dt}` and `Qd = ∫0^dt e^{A s} Qc e^{Aᵀ s} ds`.

    The Van Loan block `expm([[-A, Qc], [0, Aᵀ]] h)` holds `e^{+|λ| h}` terms
    that overflow and cancel on stiff networks when `h` is large. So it is
    evaluated on `h = dt / 2^j` with `‖A‖₁ h <= 1`, then doubled `j` times
    with `Qd(2h) = Qd(h) + Phi(h) Qd(h) Phi(h)ᵀ`: a sum of positive semidefinite
    terms, exact and stable.

    **Arguments:** `A` (1/s), `Qc` the diffusion covariance (unit²/s), `dt` (s).

    **Returns:** `(Phi, Qd)`.
    """
    n = A.shape[0]
    dt = jnp.asarray(dt, dtype=A.dtype)
    norm = jax.lax.stop_gradient(jnp.linalg.norm(A, 1) * dt)
    j = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300))), 0, _MAX_HALVINGS)
    h = dt * 2.0 ** (-j)
    M = jnp.zeros((2 * n, 2 * n), dtype=A.dtype)
    M = M.at[:n, :n].set(-A * h).at[:n, n:].set(Qc * h).at[n:, n:].set(A.T * h)
    E = _expm(M)
    Phi = E[n:, n:].T
    Qd = Phi @ E[:n, n:]
    Qd = 0.5 * (Qd + Qd.T)

    def double(i, carry):
        Phi, Qd = carry
        Qd2 = Qd + Phi @ Qd @ Phi.T
        Phi2 = Phi @ Phi
        keep = i < j
        return jnp.where(keep, Phi2, Phi), jnp.where(keep, 0.5 * (Qd2 + Qd2.T), Qd)

    return jax.lax.fori_loop(0, _MAX_HALVINGS, double, (Phi, Qd))


def sample_period(ts) -> Float[Array, ""]:
    """A run's sample period (s): the median of its time steps, so that the jitter
    docs/formats.md §1 allows (1 %) on any one step, the first included, does not set
    it; 1 for a single sample."""
    if ts.shape[0] < 2:
        return jnp.ones((), ts.dtype)
    return jnp.median(jnp.diff(ts))
