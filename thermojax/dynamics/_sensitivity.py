"""Exact output-error Jacobians by forward sensitivities through the blocked recurrence.

`jax.jacfwd` of the output-error residuals pushes every parameter's tangent
through the whole simulator: through the construction of the blocked maps and
through every large product, as many small batched products as there are
parameters. Here the work is split by size instead:

- The small part, parameters -> per-run blocked maps (discretization, powers of
  `Phi`, block-Toeplitz impulse responses, initial state), is differentiated by
  `jax.jvp`: one tangent per parameter, each a few hundred numbers.
- The large part, maps -> outputs of every sample, is bilinear in the maps and
  the block-start states, and its tangents are written out: every parameter's
  output sensitivity comes out of the *same* products as the residual, with the
  parameters as extra columns or rows (one large matrix product instead of one
  small product per parameter).

In coordinates `z[k] = x[k] - B1 u[k]` the exact-hold recurrence
`x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]` reads `z[k+1] = Phi z[k] + Bz u[k]`,
`Bz = B0 + Phi B1`, and `y[k] = C z[k] + (C B1 + D) u[k]`. Cut into blocks of `L`
samples, the outputs of block `b` are `O [u_b; s_b]` and the next block start is
`s_(b+1) = Phi^L s_b + N u_b`. The sensitivities to parameter `i` are then

    y'_b     = O'_i [u_b; s_b] + O[:, s] s'_b
    s'_(b+1) = Phi^L s'_b + (Phi^L)'_i s_b + N'_i u_b,   s'_0 = x0'_i - B1'_i u_0,

the same recurrence as the states with a drive of its own. The maps and both
recurrences are `ExactHold`'s own (`_blocked`), so the result equals `jax.jacfwd` of
the residuals to float64 roundoff.

**Layout.** Outputs and residuals are kept per block, padded to whole blocks:
(runs, blocks L, p), samples in order (`pad_to_blocks` pads). Tangents carry the
parameters last, (runs, blocks L, p, params), the layout of `jax.jacfwd`: the block
products produce it directly, and `JᵀJ` of a (rows, params) matrix is two to three
times faster on XLA's CPU kernels than that of its transpose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._blocked import (_BLOCK, block_maps, block_rows, pad_to_blocks, recurrence,
                       small_inner_product)
from ._discretize import _solve_small, discretize


def run_primal(maps, z0, u, L: int = _BLOCK):
    """Outputs (blocks L, p) of one run, padded to whole blocks, from its maps
    `(DL, N, O)` (`block_maps` with one readout) and initial `z0 = x0 - B1 u[0]`; and the
    blocks' `[inputs, start]` rows `w` (blocks, L m + n) that the tangents reuse."""
    DL, N, O = maps
    w = block_rows(DL, N, z0, u, L)
    return (w @ O.T).reshape(-1, O.shape[0] // L), w


def run_tangents(maps, dmaps, dz0, w, L: int = _BLOCK):
    """Output tangents (blocks L, p, P) of one run along `P` directions, padded to whole
    blocks, given the tangents of its maps and initial state (leading axis `P`) and `w`
    from `run_primal`."""
    return _tangents(maps, dmaps, dz0, w, L)[0]


def chunk_outputs_and_tangents(maps, dmaps, s0, ds0, u, L: int = _BLOCK):
    """One stretch of a run (`u` (blocks L, m), whole blocks) from its start `s0` (n,) and
    the start's tangents `ds0` (P, n): `(outputs (blocks L, p), tangents (blocks L, p, P),
    the next stretch's start (n,), its tangents (P, n))`. Stretches chained start to start
    give `run_primal` and `run_tangents` of the whole run (each sample depends on the ones
    before only through the block start)."""
    y, w = run_primal(maps, s0, u, L)
    dy, dstarts, drive = _tangents(maps, dmaps, ds0, w, L)
    DL = maps[0]
    ds_next = dstarts[-1] + dstarts[-1] @ DL.T + drive[-1]  # as `_next_start`
    return y, dy, _next_start(maps, w), ds_next


def chunk_outputs(maps, s0, u, L: int = _BLOCK):
    """`chunk_outputs_and_tangents` without the tangents: `(outputs (blocks L, p), the
    next stretch's start (n,))`."""
    y, w = run_primal(maps, s0, u, L)
    return y, _next_start(maps, w)


def _next_start(maps, w):
    """The block start after the last row `[u_b; s_b]` of `w`: the recurrence's own step
    `s[b+1] = s[b] + DL s[b] + N u[b]` (`DL` is `Phi^L - I`)."""
    DL, N, _ = maps
    Lm = N.shape[1]
    u_last, s_last = w[-1, :Lm], w[-1, Lm:]
    return s_last + DL @ s_last + N @ u_last


def _tangents(maps, dmaps, dz0, w, L: int):
    """`run_tangents`, the tangent block starts (blocks, P, n) and their drives (blocks,
    P, n)."""
    DL, N, O = maps
    dDL, dN, dO = dmaps
    n = DL.shape[0]
    P = dz0.shape[0]
    Lm = O.shape[1] - n
    p = O.shape[0] // L
    # Tangent block starts: s'[b+1] = Phi^L s'[b] + (dDL s[b] + dN u[b]).
    drive = w @ jnp.concatenate([jnp.transpose(dN, (2, 0, 1)).reshape(Lm, P * n),
                                 jnp.transpose(dDL, (2, 0, 1)).reshape(n, P * n)], axis=0)
    drive = drive.reshape(-1, P, n)
    dstarts = recurrence(DL, drive, dz0)  # (blocks, P, n)
    dy = w @ jnp.transpose(dO, (2, 1, 0)).reshape(Lm + n, -1)  # (blocks, L p P)
    dy = dy.reshape(-1, L * p, P) + small_inner_product(O[:, Lm:], jnp.swapaxes(dstarts, 1, 2))
    return dy.reshape(-1, p, P), dstarts, drive


def _steady_state_small(system, u0):
    """`system.steady_state(u0)` (°C) by `_solve_small`: no LAPACK in the fit loop. On a
    thermal network it solves `K x0 = G u0`, `K = -diag(c) A` symmetric: better scaled
    than `A`."""
    if system.capacitance is None:
        return _solve_small(system.A, -(system.B @ u0)[:, None])[:, 0]
    c = system.capacitance[:, None]
    return _solve_small(-c * system.A, (c * system.B) @ u0[:, None])[:, 0]


def _solve_vector_small(M, b):
    """`M⁻¹ b` for a vector `b` by `_solve_small`."""
    return _solve_small(M, b[:, None])[:, 0]


def dataset_maps(model, data, run_initial, L: int = _BLOCK):
    """Per-run `((DL, N, O), z0)` of a `ThermalModel` on a `Dataset`, stacked over runs:
    the `block_maps` of the run's outputs and its initial `z0 = x0 - B1 u[0]` (n,).

    The sample period of each run is its median step (`data.dt`), as `ExactHold` takes it.
    """
    system = model.linear_system()
    dts = jnp.asarray(data.dt, data.ts.dtype)
    # One run at a time (`lax.map`, not `vmap`): each exponential then squares only as
    # often as its own `dt` needs, in its value and in every tangent.
    discs = jax.lax.map(lambda dt: discretize(system, dt), dts)

    def one(disc, u0, r0):
        x0 = model.initial_state(system, u0, r0, steady_state=_steady_state_small,
                                 solve=_solve_vector_small)
        DL, N, (O,) = block_maps(disc.Phi, disc.B0, disc.B1, ((disc.C, disc.D),), L)
        return (DL, N, O), x0.astype(disc.Phi.dtype) - disc.B1 @ u0

    if run_initial is None:
        return jax.vmap(lambda disc, u0: one(disc, u0, None))(discs, data.inputs[:, 0])
    return jax.vmap(one)(discs, data.inputs[:, 0], run_initial)


def dataset_outputs(model, data, run_initial=None):
    """Free-run outputs (runs, T, p) of every run: `simulate_dataset` by the blocked maps."""
    return dataset_block_outputs(model, data, run_initial)[:, :data.outputs.shape[1]]


def dataset_block_outputs(model, data, run_initial=None):
    """`dataset_outputs` padded to whole blocks: (runs, blocks L, p)."""
    return block_outputs_and_states(model, data, run_initial)[0]


def block_outputs_and_states(model, data, run_initial=None):
    """`(dataset_block_outputs, states)`: a nonlinear model's node temperatures (runs, T,
    n), which `output_sensitivity_parts` can reuse at the same parameters; None for a
    linear model (its blocked recurrence keeps no per-sample states)."""
    if model.is_nonlinear:
        from ._nonlinear import dataset_states_nonlinear, readings

        x = dataset_states_nonlinear(model, data, run_initial)
        return pad_to_blocks(readings(model, x)), x
    maps, z0 = dataset_maps(model, data, run_initial)
    y = jax.vmap(lambda m, z, u: run_primal(m, z, u)[0])(maps, z0, data.inputs.astype(z0.dtype))
    return y + model.output_offset()[None, None, :], None


def output_sensitivity_parts(params_to_model, theta, data, states=None):
    """Free-run outputs of every run padded to whole blocks (runs, blocks L, p), and a
    function computing their Jacobian in `theta`: (runs, blocks L, p, P).

    `params_to_model(theta) -> (model, run_initial)`. The small part (discretization and
    block maps, with their tangents along every parameter) is computed here; the large
    part of the Jacobian when the returned function is called. `states`: a nonlinear
    model's node temperatures at `theta` (`block_outputs_and_states`), when already
    simulated.
    """

    if params_to_model(theta)[0].is_nonlinear:  # ETD2 scan, linearized per sample
        from ._nonlinear_sensitivity import dataset_outputs_and_jacobian

        y, J = dataset_outputs_and_jacobian(params_to_model, theta, data, states)
        return pad_to_blocks(y), lambda: pad_to_blocks(J)

    ((maps, z0), offset), ((dmaps, dz0), doffset) = map_tangents(params_to_model, theta, data)
    y, w = jax.vmap(run_primal)(maps, z0, data.inputs.astype(theta.dtype))

    def jacobian():
        return jax.vmap(run_tangents)(maps, dmaps, dz0, w) + doffset.T[None, None]

    return y + offset[None, None, :], jacobian


def map_tangents(params_to_model, theta, data):
    """The small part of the output Jacobian: `(((maps, z0), offset), ((dmaps, dz0),
    doffset))`, each run's `dataset_maps` and the model's output offset (p,), with their
    tangents along every parameter (runs, P, ...) and (P, p). Of the data only each
    run's period and first inputs are read."""

    def maps_of(t):
        model, run_initial = params_to_model(t)
        return dataset_maps(model, data, run_initial), model.output_offset()

    # Tangents along every parameter, (runs, P, ...); the primal does not depend on the
    # direction, so it is computed once.
    small = jax.vmap(lambda v: jax.jvp(maps_of, (theta,), (v,)), out_axes=(None, (1, 0)))(
        jnp.eye(theta.shape[0], dtype=theta.dtype))
    # Materialized before use: otherwise XLA fuses the small products that build the maps
    # into the large elementwise passes over the outputs and recomputes them per element.
    return jax.lax.optimization_barrier(small)
