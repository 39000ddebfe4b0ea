"""The constants of many laws of one shape, fitted at once (`fit_shape`): the symbolic
search's inner loop (`_symbolic_search`).

Laws of one *shape* have the same number of terms and factors per term; they differ in
which primitive and which variable each factor holds (`_symbolic_grammar`). Each
factor reads its row of tables made once per search (`primitive_tables`), so one
compiled program, `jax.vmap`-ed over the laws and over several starts of their
constants, fits them all. Per law and start, with `θ` the primitives' constants:

    r(θ) = w ⊙ (y − G(θ) β(θ)),     β(θ) = argmin_β ‖w ⊙ (y − G(θ) β − Z γ)‖²,

`G` (samples, terms) the products of the factors, `Z` nuisance columns (a heat the
fitted model already holds with a free coefficient, which a refit adjusts) and `w` the
inverse stds of the target `y`: the coefficients are solved by least squares for every
`θ` (variable projection), and `θ` by Levenberg–Marquardt with Marquardt's scaling
(`diag(JᵀJ)`), which makes the steps independent of each constant's units.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._symbolic_grammar import PRIMITIVES

LM_STEPS = 30  # Levenberg–Marquardt iterations per start
N_STARTS = 4  # starts of the constants per law (one program for every law of a shape)
CHUNK = 32  # laws per call (the last padded)
# Every law is fitted on one padded shape: two terms of two factors each, a missing
# factor the constant 1 and a missing term a zero column, so the search compiles one
# program whatever laws it tries.
MAX_TERMS, MAX_PER_TERM = 2, 2
_SHAPE = ((0, 1), (2, 3))
# A power's exponent outside this range is no law but a spike at the variable's zero
# (|ΔT|^-12 fits a few noisy samples near ΔT = 0): such a start is discarded.
EXPONENT_RANGE = (-2.0, 6.0)
_POWERS = [i for i, p in enumerate(PRIMITIVES) if p.name in ("pow", "spow")]

# Every primitive is one of three families over tables made once per search
# (`primitive_tables`): `M` (no constant), `M exp(k Z)` (pow, spow, exp, arrh) or
# `M / (1 + k Z)` (sat, rat); a factor's value costs one exponential or one division.
_FAMILY = {"x": 0, "log": 0, "inv": 0, "abs": 0, "pow": 1, "spow": 1, "exp": 1, "arrh": 1,
           "sat": 2, "rat": 2}


def primitive_tables(variables) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(M, Z, family)`: (primitives × variables, samples) tables and the family (0, 1, 2)
    of each row (row `p · V + v`: primitive `p` at variable `v`), so that the factor's
    value is `M`, `M exp(k Z)` or `M / (1 + k Z)`. Rows where a primitive does not apply
    are zero; the last two rows are the constant 1 and 0 (`fit_shape`'s padding)."""
    V = len(variables)
    N = len(variables[0].values)
    rows = len(PRIMITIVES) * V + 2  # and the constant 1, and 0
    M, Z = np.zeros((rows, N)), np.zeros((rows, N))
    fam = np.zeros(rows, np.int32)
    M[-2] = 1.0
    with np.errstate(all="ignore"):
        for p, prim in enumerate(PRIMITIVES):
            for v, var in enumerate(variables):
                row = p * V + v
                fam[row] = _FAMILY[prim.name]
                if not var.admits(prim):
                    continue
                x = np.asarray(var.values, float)
                c = var.centre(prim)
                ax = np.abs(x)
                m, z = {"x": (x, 0 * x), "log": (np.log(np.where(x > 0, x, 1.0)), 0 * x),
                        "inv": (1.0 / np.where(x > 0, x, 1.0), 0 * x), "abs": (ax, 0 * x),
                        "pow": ((x > 0).astype(float), np.log(np.where(x > 0, x, 1.0))),
                        "spow": (np.where(ax > 0, x, 0.0), np.log(np.where(ax > 0, ax, 1.0))),
                        "exp": (np.ones_like(x), x - c),
                        "arrh": (np.ones_like(x), -(1.0 / np.where(x > 0, x, 1.0) - c)),
                        "sat": (x, ax), "rat": (x, x)}[prim.name]
                M[row], Z[row] = m, z
    return M, Z, fam


def _factor(M, Z, fam, k):
    """A factor's value (samples,) from its rows of the tables and its constant `k`."""
    expo = M * jnp.exp(jnp.clip(k * Z, -60.0, 60.0))
    den = 1.0 + k * Z
    # a denominator through zero is a pole inside the data: no law
    ok = jnp.all(den > 1e-3)
    rational = jnp.where(ok, M / jnp.where(den > 1e-3, den, 1.0), jnp.nan)
    return jnp.where(fam == 0, M, jnp.where(fam == 1, expo, rational))


def _design(theta, M, Z, fam, rows, terms):
    """`G` (samples, terms) of one law: per term the product of its factors."""
    values = [_factor(M[rows[f]], Z[rows[f]], fam[rows[f]], theta[f])
              for f in range(sum(len(t) for t in terms))]
    cols = []
    for term in terms:
        col = values[term[0]]
        for f in term[1:]:
            col = col * values[f]
        cols.append(col)
    return jnp.stack(cols, 1)


def _projected(theta, M, Z, fam, rows, yw, w, Zw, terms):
    """`(r, β)`: the weighted residual after the least-squares coefficients `β` (terms
    then nuisance columns) at constants `theta`."""
    G = _design(theta, M, Z, fam, rows, terms)
    A = jnp.concatenate([G * w[:, None], Zw], 1)
    norms = jnp.sqrt(jnp.sum(A ** 2, 0))
    norms = jnp.where(norms > 0.0, norms, 1.0)
    As = A / norms[None, :]
    m = As.shape[1]
    Mat = As.T @ As + 1e-10 * jnp.eye(m)
    beta = jnp.linalg.solve(Mat, As.T @ yw)
    return yw - As @ beta, beta / norms


def _cost(r):
    c = r @ r
    return jnp.where(jnp.isfinite(c), c, jnp.inf)


def _fit_one(theta0, M, Z, fam, rows, yw, w, Zw, terms):
    """Levenberg–Marquardt from `theta0`: `(cost, θ, β)`."""
    def residual(theta):
        return _projected(theta, M, Z, fam, rows, yw, w, Zw, terms)[0]

    def body(_, state):
        theta, cost, lam = state
        r, lin = jax.linearize(residual, theta)
        J = jax.vmap(lin, out_axes=1)(jnp.eye(theta.size))
        J = jnp.where(jnp.isfinite(J), J, 0.0)
        r = jnp.where(jnp.isfinite(r), r, 0.0)
        H = J.T @ J
        d = jnp.diag(H)
        D = d + 1e-12 * jnp.max(d) + 1e-300
        step = -jnp.linalg.solve(H + lam * jnp.diag(D), J.T @ r)
        new = theta + step
        c_new = _cost(residual(new))
        ok = c_new < cost
        return (jnp.where(ok, new, theta), jnp.where(ok, c_new, cost),
                jnp.where(ok, lam / 3.0, lam * 4.0))

    cost0 = _cost(residual(theta0))
    theta, cost, _ = jax.lax.fori_loop(0, LM_STEPS, body, (theta0, cost0, 1e-2))
    _, beta = _projected(theta, M, Z, fam, rows, yw, w, Zw, terms)
    return cost, theta, beta


@functools.partial(jax.jit, static_argnames=("terms",))
def _fit_chunk(theta0, M, Z, fam, rows, yw, w, Zw, terms):
    """`_fit_one` over laws (axis 0) and their starts (axis 1 of `theta0`)."""
    def law(th0, r):
        return jax.vmap(lambda t: _fit_one(t, M, Z, fam, r, yw, w, Zw, terms))(th0)
    return jax.vmap(law)(theta0, rows)


def starts_for(tree, variables, rng: np.random.Generator) -> np.ndarray:
    """`N_STARTS` starting values (N_STARTS, factors) of a tree's constants: each
    primitive's `starts` in units of its variable's spread, combined over the factors
    (all combinations when they fit, else a sample drawn by `rng`); a factor without a
    constant has 0."""
    grids = []
    for term in tree:
        for p, v in term:
            prim, x = PRIMITIVES[p], variables[v].values
            if prim.constant is None:
                grids.append(np.zeros(1))
                continue
            unit = {"one": 1.0,
                    "rate": 1.0 / max(float(np.ptp(x)), 1e-12),
                    "inverse_rate": 1.0 / max(float(np.ptp(1.0 / np.where(x > 0, x, 1.0))),
                                              1e-12),
                    "saturation": 1.0 / max(float(np.max(np.abs(x))), 1e-12)}[prim.start_unit]
            grids.append(np.asarray(prim.starts, float) * unit)
    combos = np.stack(np.meshgrid(*grids, indexing="ij"), -1).reshape(-1, len(grids))
    if len(combos) > N_STARTS:
        combos = combos[np.sort(rng.choice(len(combos), N_STARTS, replace=False))]
    reps = -(-N_STARTS // len(combos))
    return np.tile(combos, (reps, 1))[:N_STARTS]


def fit_shape(trees, variables, tables, yw, w, Zw, rng: np.random.Generator):
    """Fit every tree of `trees` (one shape) to the weighted target.

    **Arguments:**

    - `trees`: canonical trees (`_symbolic_grammar.Tree`) of at most `MAX_TERMS` terms
      of at most `MAX_PER_TERM` factors.
    - `variables`: the grammar's `Variable`s; `tables` their `primitive_tables`.
    - `yw` (samples,): the target times `w`, the inverse stds (samples,).
    - `Zw` (samples, z): nuisance columns times `w` (z may be 0).

    **Returns:** per tree `(cost, θ (factors,), β (terms,))` of its best start: the
    weighted sum of squares, the constants and the coefficients.
    """
    V = len(variables)
    one, zero = len(PRIMITIVES) * V, len(PRIMITIVES) * V + 1
    rows = np.full((len(trees), 2 * MAX_PER_TERM), one, np.int32)
    for i, t in enumerate(trees):
        for j in range(MAX_TERMS):
            if j >= len(t):
                rows[i, j * MAX_PER_TERM] = zero  # no such term: a zero column
                continue
            for f, (p, v) in enumerate(t[j]):
                rows[i, j * MAX_PER_TERM + f] = p * V + v
    theta0 = np.stack([_padded(t, starts_for(t, variables, rng)) for t in trees])
    out = []
    M, Z, fam = tables
    M, Z, yw, w, Zw = (jnp.asarray(a, float) for a in (M, Z, yw, w, Zw))
    fam = jnp.asarray(fam)
    for k in range(0, len(trees), CHUNK):
        idx = np.arange(k, min(k + CHUNK, len(trees)))
        pad = np.concatenate([idx, np.full(CHUNK - len(idx), idx[0])])
        cost, theta, beta = (np.asarray(a) for a in _fit_chunk(
            jnp.asarray(theta0[pad]), M, Z, fam, jnp.asarray(rows[pad]), yw, w, Zw, _SHAPE))
        slot_prims = rows[pad] // V  # (laws, slots); padding rows are past the last
        powers = np.isin(slot_prims, _POWERS)[:, None, :]
        wild = np.any(powers & ((theta < EXPONENT_RANGE[0]) | (theta > EXPONENT_RANGE[1])),
                      -1)
        cost = np.where(wild | ~np.isfinite(cost), np.inf, cost)
        for j in range(len(idx)):
            s = int(np.argmin(cost[j]))
            t = trees[idx[j]]
            flat = [theta[j, s, k * MAX_PER_TERM + f] for k, term in enumerate(t)
                    for f in range(len(term))]
            out.append((float(cost[j, s]), np.array(flat), beta[j, s, :len(t)]))
    return out


def _padded(tree, starts):
    """Starts (N_STARTS, factors of `tree`) laid out on the padded shape's slots."""
    out = np.zeros((starts.shape[0], MAX_TERMS * MAX_PER_TERM))
    k = 0
    for j, term in enumerate(tree):
        for f in range(len(term)):
            out[:, j * MAX_PER_TERM + f] = starts[:, k]
            k += 1
    return out
