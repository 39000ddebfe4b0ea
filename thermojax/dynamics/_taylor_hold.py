"""The exact-hold recurrence of a large network by the exponential times a vector: no
`n × n` exponential, the network's sparse structure used.

Over one sample period the inputs move as their holds say (`u(t) = u_k + (t - t_k) b_k`,
`b_k = (u_(k+1) - u_k)/dt` on first-order-hold inputs, 0 on zero-order ones), so the
augmented state `[x; u; b]` obeys `d/dt [x; u; b] = M [x; u; b]`,
`M = [[A, B, 0], [0, 0, I], [0, 0, 0]]`: the augmented matrix of `discretize`. Its
exponential times the vector is summed as a Taylor series in `s` substeps of
`h = dt / s` (Al-Mohy and Higham 2011), with `x` terms

    x_1 = h (A x + B u),   x_2 = (h/2) (A x_1 + h B b),   x_j = (h/j) A x_(j-1), j > 2,

and `u <- u + h b` after each substep: `2 + (d - 1)` products with `A` per substep, which
on a network of `e` links cost `O(n + e)` each (the non-zeros of `A`, gathered once per
evaluation), against `O(n³)` for the dense exponential and its block maps (`_blocked`).
The degree `d` and `s` are chosen from a bound on `‖M h‖₁` so that the truncation error is
below float64 roundoff (`taylor_plan`): the same exact discretization as `discretize`,
summed another way.

Reverse mode: each sample period is `jax.checkpoint`ed, so a gradient keeps one state
vector per sample (`(times, n)`) and recomputes the Taylor terms of one period at a
time: memory bounded by the states, not by the samples × the parameters.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

# Relative truncation error accepted of a substep's series (float64 unit roundoff).
_TOL = 2.0 ** -53
_MAX_DEGREE = 40


def _theta(degree: int) -> float:
    """The largest `‖M h‖₁` for which the Taylor remainder of `degree`,
    `θ^(d+1)/(d+1)! · e^θ`, stays below `_TOL` (bisection; host-side)."""
    lo, hi = 0.0, 50.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        bound = math.exp((degree + 1) * math.log(mid) - math.lgamma(degree + 2) + mid)
        lo, hi = (mid, hi) if bound <= _TOL else (lo, mid)
    return lo


_THETAS = {d: _theta(d) for d in range(4, _MAX_DEGREE + 1)}


def taylor_plan(norm: float) -> tuple[int, int]:
    """`(substeps, degree)` with the fewest products with `A` whose series is exact to
    roundoff for a sample period of `‖M dt‖₁ <= norm` (dimensionless)."""
    best = None
    for d, theta in _THETAS.items():
        s = max(1, math.ceil(norm / theta))
        if best is None or s * d < best[0] * best[1]:
            best = (s, d)
    return best


def sparsity(*matrices) -> tuple[np.ndarray, np.ndarray]:
    """The non-zeros in any of the same-shaped `matrices` (NumPy) in row-padded form:
    `cols` (rows, K) the column of each row's `k`-th non-zero and `real` (rows, K) bool,
    False in the padding (a row with fewer than `K` non-zeros repeats column 0). A
    product then gathers and sums `K` entries per row: no scatter."""
    nz = np.zeros(np.shape(matrices[0]), bool)
    for M in matrices:
        nz |= np.asarray(M) != 0
    K = max(int(nz.sum(1).max()), 1)
    cols = np.zeros((nz.shape[0], K), np.int32)
    real = np.zeros((nz.shape[0], K), bool)
    for i, row in enumerate(nz):
        c = np.flatnonzero(row)
        cols[i, :c.size], real[i, :c.size] = c, True
    return cols, real


def gathered(M, cols: np.ndarray, real: np.ndarray):
    """The entries of `M` (rows, n) at `sparsity`'s `cols`, zero in the padding: (rows, K)."""
    return jnp.where(real, jnp.take_along_axis(M, jnp.asarray(cols), axis=1), 0.0)


def sparse_matvec(values, cols: np.ndarray, x):
    """`M x` (rows,) for `M` given by `gathered` entries `values` (rows, K) at `cols`."""
    return jnp.sum(values * x[cols], axis=-1)


def diagonals(nonzero: np.ndarray) -> np.ndarray | None:
    """The offsets `k` (`A[i, i + k]`) holding every non-zero of the pattern `nonzero`
    (rows, n) bool, when there are at most twice as many as the widest row's non-zeros
    (a chain: -1, 0, 1; a grid in row order: -w, -1, 0, 1, w); else None."""
    rows, cols = np.nonzero(nonzero)
    offsets = np.unique(cols - rows)
    width = max(int(nonzero.sum(1).max()), 1)
    return offsets.astype(np.int32) if offsets.size <= 2 * width else None


def diagonal_values(M, offsets: np.ndarray):
    """`d[j, i] = M[i, i + offsets[j]]` (0 outside the matrix): (offsets, n)."""
    n = M.shape[0]
    i = np.arange(n)
    out = []
    for k in offsets:
        j = i + int(k)
        inside = (j >= 0) & (j < n)
        out.append(jnp.where(inside, M[i, np.clip(j, 0, n - 1)], 0.0))
    return jnp.stack(out)


def diagonal_matvec(d, offsets: np.ndarray, x):
    """`M x` from `diagonal_values` `d`: a sum of shifted copies of `x`, elementwise work
    whose transpose is again shifts (a product by gathered entries transposes to a
    scatter, several times slower on CPU)."""
    n = x.shape[-1]
    y = jnp.zeros_like(x)
    for row, k in zip(d, offsets):
        k = int(k)
        if k == 0:
            shifted = x
        elif k > 0:
            shifted = jnp.concatenate([x[..., k:], jnp.zeros_like(x[..., :k])], axis=-1)
        else:
            shifted = jnp.concatenate([jnp.zeros_like(x[..., n + k:]), x[..., :n + k]], axis=-1)
        y = y + row * shifted
    return y


def taylor_states(matvec, B: Float[Array, "n m"], x0: Float[Array, " n"],
                  u: Float[Array, "times m"], dt, foh: np.ndarray, substeps: int,
                  degree: int, checkpoint: bool = True) -> Float[Array, "times n"]:
    """States `x[0..T-1]` of `x' = A x + B u(t)`, `x[0] = x0`, exact between samples for
    each input's hold.

    **Arguments:**

    - `matvec`: `x -> A x` (1/s · °C), a closure over `A` (dense or sparse).
    - `B`: (n, m) input matrix; `u`: (times, m) inputs; `x0`: (n,) °C; `dt`: s.
    - `foh`: (m,) bool, static: first-order-hold inputs (the others zero-order).
    - `substeps`, `degree`: from `taylor_plan` of a bound on `‖A dt‖₁`.
    - `checkpoint`: recompute each period's terms in reverse mode (memory of one state
      per sample); False keeps them (memory `degree` times that, for a linearization
      whose products are then pure tangent work).

    **Returns:** (times, n) °C.
    """
    h = dt / substeps
    slope_mask = jnp.asarray(np.asarray(foh, bool))
    higher = jnp.arange(3, degree + 1, dtype=x0.dtype)  # the terms past the second

    def period(x, uu):
        uk, uk1 = uu
        b = jnp.where(slope_mask, (uk1 - uk) / dt, 0.0)
        Bb = B @ b

        def term(carry, k):
            t, total = carry
            t = (h / k) * matvec(t)
            return (t, total + t), None

        def substep(x, j):
            a = uk + (j * h) * b
            t1 = h * (matvec(x) + B @ a)
            t2 = (h / 2) * (matvec(t1) + h * Bb)
            (_, total), _ = jax.lax.scan(term, (t2, x + t1 + t2), higher)
            return total, None

        x_next, _ = jax.lax.scan(substep, x, jnp.arange(substeps, dtype=x0.dtype))
        return x_next, x_next

    if checkpoint:
        period = jax.checkpoint(period)
    _, xs = jax.lax.scan(period, x0, (u[:-1], u[1:]))
    return jnp.concatenate([x0[None], xs])


class SparsePlan:
    """What a model's Taylor simulation needs fixed before tracing (hashable, host-side):
    the non-zeros of `A` and of the readout `C`, and the substeps and degree of a bound
    on `‖M dt‖₁`. Built by `sparse_plan` from the model's values (at one or more
    parameter points: their union of non-zeros)."""

    def __init__(self, a_cols, a_real, c_cols, c_real, substeps: int, degree: int,
                 norm: float, offsets=None):
        self.a_cols, self.a_real = a_cols, a_real
        self.offsets = offsets  # `diagonals` of A, or None (products by gathered entries)
        self.c_cols, self.c_real = c_cols, c_real
        self.substeps, self.degree, self.norm = int(substeps), int(degree), float(norm)
        self._key = (a_cols.tobytes(), a_real.tobytes(), a_cols.shape, c_cols.tobytes(),
                     c_real.tobytes(), c_cols.shape, self.substeps, self.degree,
                     None if offsets is None else offsets.tobytes())

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, SparsePlan) and self._key == other._key


def period_norm(system, dt: float) -> float:
    """`‖A dt‖₁` of `system` (host-side), at least 1: what bounds the series' terms past
    the first. The inputs enter only the first two terms, and scaling `u` scales them
    alike: `B` does not slow the convergence."""
    return float(max(np.abs(np.asarray(system.A)).sum(0).max() * dt, 1.0))


def sparse_plan(systems, dt_max: float, margin: float = 1.25) -> SparsePlan:
    """The `SparsePlan` of `systems` (`LinearSystem`s of one model at several parameter
    points; NumPy values) for sample periods up to `dt_max` (s), the norm bound `margin`
    times the largest found (room for the parameters to move)."""
    norm = margin * max(period_norm(s, dt_max) for s in systems)
    nonzero = np.any([np.asarray(s.A) != 0 for s in systems], axis=0)
    return SparsePlan(*sparsity(*[s.A for s in systems]), *sparsity(*[s.C for s in systems]),
                      *taylor_plan(norm), norm, diagonals(nonzero))


def plan_norm(system, plan: SparsePlan, dt):
    """`‖A dt‖₁` of a traced `system` (what `plan.norm` must bound for its series to be
    exact)."""
    return jnp.maximum(jnp.max(jnp.sum(jnp.abs(system.A), axis=0)) * dt, 1.0)


def model_outputs_taylor(model, system, plan: SparsePlan, x0, u, dt, checkpoint: bool = True):
    """Outputs `C x + D u + offset` (times, p) of one run of a linear `model` (its
    `LinearSystem` `system`) by `taylor_states` with `plan`'s structure and substeps."""
    if plan.offsets is not None:
        a_diag = diagonal_values(system.A, plan.offsets)

        def matvec(x):
            return diagonal_matvec(a_diag, plan.offsets, x)
    else:
        a_vals = gathered(system.A, plan.a_cols, plan.a_real)

        def matvec(x):
            return sparse_matvec(a_vals, plan.a_cols, x)

    c_vals = gathered(system.C, plan.c_cols, plan.c_real)
    foh = np.array([h == "foh" for h in system.holds], bool)
    xs = taylor_states(matvec, system.B, x0, u, dt, foh, plan.substeps, plan.degree,
                       checkpoint)
    y = jnp.sum(xs[:, plan.c_cols] * c_vals[None], axis=-1)
    return y + u @ system.D.T + model.output_offset()[None, :]
