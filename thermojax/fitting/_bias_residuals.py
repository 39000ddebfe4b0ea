"""Bias columns inside the output-error likelihood, by variable projection (docs/formats.md §4).

A bias column is a measured output whose prediction is linear in its coefficients once
the node temperatures `x` and the relaxation times `τ` are given:

    b = X(x, ẋ, τ) c,   X = [(T − 25)^p | T_a − T_b | ẋ_n | T_v − ε_v(τ_v)],

`ẋ = A x + B u` (plus the nonlinear right-hand side) being the model's exact state
derivative at the sample, and `ε_v` the strain lag `dε/dt = (T_v − ε)/τ_v`, `ε(0) =
T_v(0)`, exact for node temperatures linear between samples. In every evaluation the
coefficients are solved by weighted least squares (variable projection, Golub & Pereyra
1973), so the residual `(y − X ĉ)/σ` is a function of the thermal parameters and the
τ's alone and the thermal fit feels the bias data. Its Jacobian is pushed forward from
the states' sensitivities with `jax.jvp`: the exact variable-projection derivative.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..compilation._traced_cache import stored_jit
from ..dynamics._blocked import pad_to_blocks
from ..dynamics._sensitivity import dataset_block_outputs
from ..model._spec import ModelSpec
from ._bias import Strain, static_columns, strains_of

_RIDGE = 1e-10  # relative Tikhonov term of the scaled normal equations (rank-safe)


@dataclass(frozen=True)
class ColumnDesign:
    """The regressors of one bias column, as node indices of the lowered spec.

    `strains` index `FitState.bias_log_tau`; `strain_nodes` are their nodes; `fixed_k`
    holds a fixed gain (column unit per K) or None where `k` is fitted.
    """

    temperature: int
    order: int
    gradients: tuple[tuple[int, int], ...]
    rates: tuple[int, ...]
    strains: tuple[int, ...]
    strain_nodes: tuple[int, ...]
    fixed_k: tuple[float | None, ...]


class BiasColumns(eqx.Module):
    """The measured bias columns of every run, padded to whole blocks, and their designs."""

    y: jax.Array  # (runs, blocks L, q), 0 where not measured
    mask: jax.Array  # (runs, blocks L, q) bool
    designs: tuple[ColumnDesign, ...] = eqx.field(static=True)
    columns: tuple[str, ...] = eqx.field(static=True)


def spec_strains(spec: ModelSpec) -> list[Strain]:
    """The viscoelastic effects of `spec` in `FitState.bias_log_tau` order."""
    return strains_of(spec.biases, spec.effects)


def bias_columns(spec: ModelSpec, experiments, holdout: int | None = None
                 ) -> BiasColumns | None:
    """The bias data of `experiments` (each with `.biases`, see `Experiment`) laid out for
    `spec` (lowered: node indices as the fit's states), or None without bias channels."""
    if not spec.biases:
        return None
    idx = {n: i for i, n in enumerate(spec.node_names)}
    strains = spec_strains(spec)
    designs = []
    for b in spec.biases:
        mine = [(i, s) for i, s in enumerate(strains) if s.column == b.column]
        designs.append(ColumnDesign(
            idx[b.temperature], b.order, tuple((idx[a], idx[c]) for a, c in b.gradients),
            tuple(idx[n] for n in b.rates), tuple(i for i, _ in mine),
            tuple(idx[s.node] for _, s in mine),
            tuple(s.k.value if s.k is not None and s.k.fixed else None for _, s in mine)))
    longest = max(e.n_times for e in experiments)
    y = np.zeros((len(experiments), longest, len(spec.biases)))
    mask = np.zeros(y.shape, bool)
    for r, e in enumerate(experiments):
        measured = np.isfinite(e.biases)
        y[r, :e.n_times] = np.where(measured, e.biases, 0.0)
        mask[r, :e.n_times] = measured & (r != holdout)
    return BiasColumns(*jax.device_put((np.asarray(pad_to_blocks(y)),
                                        np.asarray(pad_to_blocks(mask)))),
                       tuple(designs), tuple(b.column for b in spec.biases))


def _strain(T, dt, log_tau):
    """`T − ε` (runs, L) of node temperatures `T` (runs, L) °C with run periods `dt`
    (runs,) s: the first-order-hold lag of `dynamics._lag.first_order_lag`."""
    r = dt / jnp.exp(log_tau)
    one_minus_a = -jnp.expm1(-r)
    a = 1.0 - one_minus_a
    beta = one_minus_a / r
    b1, b0 = 1.0 - beta, beta - a  # weights of T[k+1] and T[k]
    dev = T - T[:, :1]

    def step(eps, pair):
        prev, new = pair
        eps = a * eps + b1 * new + b0 * prev
        return eps, eps

    _, eps = jax.lax.scan(step, jnp.zeros_like(dt), (dev[:, :-1].T, dev[:, 1:].T))
    eps = jnp.concatenate([jnp.zeros_like(dt)[None], eps]).T
    return dev - eps


def state_derivative(model, x, inputs):
    """The model's exact `dx/dt` (runs, T, n) in K/s at the samples: `A x + B u` plus the
    nonlinear terms, from node temperatures `x` (runs, T, n) °C and inputs (runs, T, m)."""
    system = model.linear_system()
    xdot = x @ system.A.T + inputs @ system.B.T
    if model.is_nonlinear:
        xdot = xdot + jax.vmap(jax.vmap(lambda xi, ui: model.nonlinear_rate(system, xi, ui)))(
            x, inputs)
    return xdot


@stored_jit
def node_temperatures(model, data, run_initial):
    """Free-run node temperatures and their exact derivatives, each (runs, T, n): °C, K/s."""
    T, p = data.outputs.shape[1:]
    y = dataset_block_outputs(dataclasses.replace(model, read_states=True), data, run_initial)
    x = y[:, :T, p:]
    return x, state_derivative(model, x, data.inputs.astype(x.dtype))


def design_matrices(model, log_tau, x, inputs, dt, bias: BiasColumns):
    """Per column: its regressors (runs, blocks L, m_j) and its fixed-gain part (runs,
    blocks L), from node temperatures `x` (runs, blocks L, n) °C, padded `inputs`
    (runs, blocks L, m) and run periods `dt` (runs,) s."""
    xdot = state_derivative(model, x, inputs)
    out = []
    for d in bias.designs:
        cols = static_columns(x, xdot, d.temperature, d.order, d.gradients, d.rates)
        fixed = jnp.zeros_like(cols[0])
        for s, node, k in zip(d.strains, d.strain_nodes, d.fixed_k):
            z = _strain(x[..., node], dt, log_tau[s])
            if k is None:
                cols.append(z)
            else:
                fixed = fixed + k * z
        out.append((jnp.stack(cols, axis=-1), fixed))
    return out


def least_squares(X, y, w):
    """Weighted least squares `argmin Σ w (y − X c)²` over rows (..., m) by scaled normal
    equations with a tiny ridge (a rank-deficient design still gives finite values and
    derivatives). Returns `c` (m,)."""
    X2 = X.reshape(-1, X.shape[-1]) * w.reshape(-1, 1)
    y2 = y.reshape(-1) * w.reshape(-1)
    scale = jnp.sqrt(jnp.sum(X2 ** 2, axis=0) / jnp.maximum(jnp.sum(w ** 2), 1.0))
    scale = jnp.where(scale > 0, scale, 1.0)
    Xs = X2 / scale[None, :]
    G = Xs.T @ Xs
    G = G + _RIDGE * jnp.trace(G) / G.shape[0] * jnp.eye(G.shape[0], dtype=G.dtype)
    return jnp.linalg.solve(G, Xs.T @ y2) / scale


def project(model, log_tau, x, inputs, dt, bias: BiasColumns, sigma):
    """Every bias column's weighted residuals, a tuple of (runs, blocks L), zero where
    not measured, and its least-squares coefficients, a tuple of (m_j,) in
    `design_matrices` order; `sigma` (q,) in column units."""
    residuals, coefficients = [], []
    for j, (X, fixed) in enumerate(design_matrices(model, log_tau, x, inputs, dt, bias)):
        w = bias.mask[..., j].astype(x.dtype)
        target = bias.y[..., j] - fixed
        c = least_squares(X, target, w)
        residuals.append(w * (target - X @ c) / sigma[j])  # X @ c: (runs, L, m) @ (m,)
        coefficients.append(c)
    return tuple(residuals), tuple(coefficients)


def bias_residuals(model, log_tau, x, inputs, dt, bias: BiasColumns, sigma):
    """The residuals of `project`: the coefficients projected out."""
    return project(model, log_tau, x, inputs, dt, bias, sigma)[0]


def pushed_forward(model_of, theta, x, dx, inputs, dt, bias: BiasColumns, sigma):
    """`project` at `theta` and its derivative along every parameter: `(residuals,
    coefficients)` and their Jacobians (each leaf with a last axis of `P`), from the
    states `x` (runs, blocks L, n) and their sensitivities `dx` (runs, blocks L, n, P);
    `model_of(theta) -> (model, log_tau)`. This is the exact derivative of the
    projected residuals (Golub & Pereyra), not Kaufman's approximation."""

    def f(t, xs):
        model, log_tau = model_of(t)
        return project(model, log_tau, xs, inputs, dt, bias, sigma)

    eye = jnp.eye(theta.shape[0], dtype=theta.dtype)
    return jax.vmap(lambda e, d: jax.jvp(f, (theta, x), (e, d)), in_axes=(0, 3),
                    out_axes=(None, -1))(eye, dx)
