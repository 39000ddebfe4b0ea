"""The exact-hold recurrence cut into blocks: one implementation for `ExactHold` and for
the fit's forward sensitivities (`_sensitivity`).

With `z[k] = x[k] - B1 u[k]` the recurrence `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]`
becomes `z[k+1] = Phi z[k] + Bz u[k]`, `Bz = B0 + Phi B1`, which only looks back, and a
readout `y = C x + D u` becomes `y[k] = C z[k] + (C B1 + D) u[k]`. It is cut into blocks
of `L = _BLOCK` samples. Inside a block every readout is a linear map `O` of the block's
inputs and first `z` (powers of Phi and a block-Toeplitz matrix of the impulse response),
so all blocks of all (vmapped) runs are evaluated by one matrix product: BLAS work
instead of a long chain of tiny steps. Only the block starts are sequential; they obey
the same kind of recurrence, `s[b+1] = Phi^L s[b] + N u_b`, which is blocked the same
way (`_SUPER` blocks per level) until at most `_SEQ_MAX` steps remain for a `lax.scan`.

It is the same linear map as the step-by-step recurrence, summed in another order, so
equal to it to float64 roundoff: against the recurrence run in extended precision, 1e-15
to 3e-15 relative on imu6 and random networks, 2e-14 at worst (tau_max/dt ~ 5e4 over
144,000 steps), where a float64 step-by-step scan is at 6e-15 to 1e-14.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

_BLOCK = 16  # samples per block
_SUPER = 8  # blocks per super-block of the block-start recurrence
_SEQ_MAX = 128  # at most this many steps are left to a sequential scan
_SMALL_INNER = 32  # `small_inner_product` sums at most this many broadcast products


def powers_minus_identity(D: Float[Array, "n n"], k: int) -> Float[Array, "powers n n"]:
    """`P^j - I` for `j = 0..k`, given `D = P - I`.

    Built as `D_(j+1) = D_j + D + D D_j`, so each is accurate relative to its own (small,
    for slow modes) size. Forming `P^j` by repeated products instead loses that: its
    rounding, of order `j eps`, is amplified by `1/(1 - rho^j)` in the block-start
    recurrence, up to ~1e-13 relative on slow (tau/dt ~ 1e4) networks. A scan, not an
    unrolled loop: the same values, a third of the compile time under `jax.jvp`.
    """

    def step(out, _):
        out = out + D + D @ out
        return out, out

    _, out = jax.lax.scan(step, jnp.zeros_like(D), None, length=k)
    return jnp.concatenate([jnp.zeros_like(D)[None], out])


def small_inner_product(a, b):
    """`a @ b` (broadcast over leading axes) for a short inner dimension (the nodes):
    a sum of broadcast products, one fused elementwise pass. XLA's CPU matrix kernels
    take up to ten times longer on such shapes. A plain `@` beyond `_SMALL_INNER`."""
    if a.shape[-1] > _SMALL_INNER:
        return a @ b
    rank = max(a.ndim, b.ndim)
    a = a.reshape((1,) * (rank - a.ndim) + a.shape)
    b = b.reshape((1,) * (rank - b.ndim) + b.shape)
    return sum(a[..., :, i:i + 1] * b[..., i:i + 1, :] for i in range(a.shape[-1]))


def _lagged(x, L: int):
    """`t[j, i] = x[j - 1 - i]` for `i < j`, else 0, from `x` of shape (L, ...): (L, L, ...)."""
    d = np.arange(L)[:, None] - 1 - np.arange(L)[None, :]
    real = jnp.asarray(d >= 0).reshape(L, L, *(1,) * (x.ndim - 1))
    return jnp.where(real, x[np.clip(d, 0, L - 1)], 0.0)


def block_maps(Phi: Float[Array, "n n"], B0: Float[Array, "n m"], B1: Float[Array, "n m"],
               readouts, L: int = _BLOCK):
    """The blocked form `(DL, N, Os)` of one run's recurrence.

    **Arguments:**

    - `Phi`, `B0`, `B1`: the `DiscreteSystem`'s matrices.
    - `readouts`: a tuple of `(C, D)` pairs, `C` (p, n) and `D` (p, m), each a readout
      `C x + D u` (`(I, 0)` reads the states).
    - `L`: samples per block.

    **Returns:** `DL = Phi^L - I` (n, n) and `N` (n, L m), with which block starts obey
    `s_(b+1) = s_b + DL s_b + N u_b`; and one `O` (L p, L m + n) per readout, mapping a
    block's `[u_b; s_b]` (inputs in sample order, then its start `z`) to its readouts in
    sample order.
    """
    n, m = B0.shape
    eye = jnp.eye(n, dtype=Phi.dtype)
    Bz = B0 + Phi @ B1
    dpows = powers_minus_identity(Phi - eye, L)
    pows = dpows + eye[None]
    PB = pows[:L] @ Bz  # (L, n, m): Phi^k Bz
    N = jnp.transpose(PB[::-1], (1, 0, 2)).reshape(n, L * m)  # [:, i] = Phi^(L-1-i) Bz
    Os = []
    for C, D in readouts:
        p = C.shape[0]
        hy = _lagged(small_inner_product(C, PB), L)  # [j, i] = C Phi^(j-1-i) Bz
        hy = jnp.transpose(hy, (0, 2, 1, 3)).reshape(L * p, L * m)
        hy = hy + jnp.kron(jnp.eye(L, dtype=Phi.dtype), C @ B1 + D)
        CP = small_inner_product(C, pows[:L]).reshape(L * p, n)
        Os.append(jnp.concatenate([hy, CP], axis=1))
    return dpows[L], N, tuple(Os)


def recurrence(D: Float[Array, "n n"], e: Float[Array, "K rows n"], s0: Float[Array, "rows n"]
               ) -> Float[Array, "K rows n"]:
    """`s[0] = s0`, `s[k+1] = s[k] + D s[k] + e[k]` for a batch of rows: `s[0..K-1]`
    (`e[K-1]` is unused). Super-blocks of `_SUPER` steps, evaluated by matrix products,
    until at most `_SEQ_MAX` sequential steps remain."""
    K, R, n = e.shape
    if K <= _SEQ_MAX:
        def step(x, ek):
            return x + (x @ D.T + ek), x

        # Not unrolled: at most _SEQ_MAX cheap steps, and unrolling 8x cost ~0.6 s of compile.
        return jax.lax.scan(step, s0, e)[1]
    L = _SUPER
    ns = -(-K // L)
    if ns * L != K:
        e = jnp.concatenate([e, jnp.zeros((ns * L - K, R, n), e.dtype)])
    dpows = powers_minus_identity(D, L)
    pows = dpows + jnp.eye(n, dtype=D.dtype)[None]
    eb = jnp.transpose(e.reshape(ns, L, R, n), (0, 2, 1, 3)).reshape(ns, R, L * n)
    # Super-block starts: S[c+1] = P^L S[c] + sum_i P^(L-1-i) e[cL+i].
    into_next = jnp.transpose(pows[L - 1::-1], (1, 0, 2)).reshape(n, L * n)
    starts = recurrence(dpows[L], eb @ into_next.T, s0)  # (ns, R, n)
    # Inside: s[cL+j] = P^j S[c] + sum_{i<j} P^(j-1-i) e[cL+i].
    tz = _lagged(pows[:L], L)  # (L, L, n, n)
    expand = jnp.concatenate([jnp.transpose(tz, (0, 2, 1, 3)).reshape(L * n, L * n),
                              pows[:L].reshape(L * n, n)], axis=1)
    s = jnp.concatenate([eb, starts], axis=2) @ expand.T  # (ns, R, L n)
    s = jnp.transpose(s.reshape(ns, R, L, n), (0, 2, 1, 3)).reshape(ns * L, R, n)
    return s[:K]


def block_rows(DL: Float[Array, "n n"], N: Float[Array, "n block_inputs"], z0: Float[Array, " n"],
               u: Float[Array, "times m"], L: int = _BLOCK) -> Float[Array, "blocks row"]:
    """Each block's `[u_b; s_b]` row (blocks, L m + n) of one run, from `block_maps`' `DL`,
    `N`, the initial `z0 = x0 - B1 u[0]` and the inputs (times, m). The last input is held
    to fill the last block: padded samples only follow the real ones."""
    T, m = u.shape
    nb = -(-T // L)
    if nb * L != T:
        u = jnp.concatenate([u, jnp.broadcast_to(u[-1], (nb * L - T, m))])
    ub = u.reshape(nb, L * m)
    starts = recurrence(DL, (ub @ N.T)[:, None, :], z0[None, :])[:, 0, :]
    return jnp.concatenate([ub, starts], axis=1)


def pad_to_blocks(x, L: int = _BLOCK):
    """Per-sample values (runs, T, ...) zero-padded to whole blocks: (runs, blocks L, ...)."""
    pad = -x.shape[1] % L
    return jnp.concatenate([x, jnp.zeros((x.shape[0], pad, *x.shape[2:]), x.dtype)], axis=1)
