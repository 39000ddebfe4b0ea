"""Output Jacobians of a nonlinear model (ETD2) by per-sample linearization.

`jax.jacfwd` of the ETD2 scan (`_nonlinear`) pushes every parameter's tangent through
every substep of every sample, one small operation at a time: the loop body grows
with the tangents and the work is dispatch-bound (about 15 times the simulation on
imu6). Here the chain rule is taken in another order:

1. the scan runs once, giving the states `x_k`;
2. each sample's step map `x_k+1 = F(x_k, u_k, u_k+1; θ)` is differentiated at its own
   `x_k`, vectorized over a chunk of samples: `F_x` (n, n) and `F_θ` (n, P);
3. the state sensitivities `S_k = dx_k/dθ` (n, P) follow the linear recurrence
   `S_k+1 = F_x(k) S_k + F_θ(k)`, `S_0 = dx_0/dθ`: one small product per sample;
4. the readings' sensitivities are `dy_k = g_x S_k + g_θ` (`g` the read-out `C x + offset`).

The products are the same as `jax.jacfwd`'s, so the result equals it to roundoff
(tests/test_nonlinear_sensitivity.py). Chunks of `_CHUNK` samples bound the memory of
the per-sample derivatives to (chunk, n, n + P) per run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._discretize import sample_period
from ._nonlinear import (etd2_matrices, etd2_step, initial_state_nonlinear,
                         simulate_run_nonlinear)

_CHUNK = 64  # samples differentiated in one vectorized pass


def _readout(model, system, x):
    """Readings (outputs,) of the node temperatures `x` (nodes,)."""
    return system.C @ x + model.output_offset()


def run_outputs_and_jacobian(params_to_model, theta, ts, u, run: int | jax.Array):
    """Free-run readings (T, p) of one run of a nonlinear model and their Jacobian in
    `theta` (T, p, P).

    `params_to_model(theta) -> (model, run_initial)`, `run_initial` (runs, k) or None;
    `ts` (T,) s, `u` (T, m) the run's inputs, `run` its index in `run_initial`.
    """

    def parts(t):
        model, run_initial = params_to_model(t)
        return model, model.linear_system(), None if run_initial is None else run_initial[run]

    def initial(t):
        model, system, r0 = parts(t)
        return initial_state_nonlinear(model, system, u[0], r0)

    dt = sample_period(ts)
    P = theta.shape[0]
    # The step's matrices and their tangents along every parameter, once per run.
    mats, dmats = jax.vmap(lambda v: jax.jvp(lambda t: etd2_matrices(parts(t)[1], dt),
                                             (theta,), (v,)), out_axes=(None, 0))(
        jnp.eye(P, dtype=theta.dtype))

    def step(t, matrices, x, u_k, u_k1):
        model, system, _ = parts(t)
        return etd2_step(model, system, dt, matrices=matrices)(x, u_k, u_k1)

    def readout(t, x):
        model, system, _ = parts(t)
        return _readout(model, system, x)

    model, system, _ = parts(theta)
    x = simulate_run_nonlinear(model, system, ts, u, initial(theta))  # (T, n)
    y = jax.vmap(lambda xk: _readout(model, system, xk))(x)

    T = x.shape[0]
    pad = -T % _CHUNK
    u_next = jnp.concatenate([u[1:], u[-1:]], axis=0)

    def chunks(a):  # (T, ...) -> (T / chunk, chunk, ...), padded with the last sample
        a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)], axis=0)
        return a.reshape(-1, _CHUNK, *a.shape[1:])

    n_dirs = P + x.shape[1]  # every parameter, then every state
    t_dirs = jnp.eye(n_dirs, P, dtype=theta.dtype)
    m_dirs = jax.tree.map(lambda d: jnp.concatenate([d, jnp.zeros((n_dirs - P, *d.shape[1:]),
                                                                  d.dtype)]), dmats)
    x_dirs = jnp.eye(n_dirs, x.shape[1], -P, dtype=theta.dtype)

    def step_jac(xk, uk, uk1):  # (n, P + n): dF/dθ, then dF/dx
        zero = jnp.zeros_like(uk)
        tangents = jax.vmap(lambda dt_, dm, dx: jax.jvp(
            step, (theta, mats, xk, uk, uk1), (dt_, dm, dx, zero, zero))[1])(
            t_dirs, m_dirs, x_dirs)
        return tangents.T

    def read_jac(xk):  # (p, P + n)
        tangents = jax.vmap(lambda dt_, dx: jax.jvp(readout, (theta, xk), (dt_, dx))[1])(
            t_dirs, x_dirs)
        return tangents.T

    def chunk(S, inp):
        xc, uc, unc = inp
        F = jax.vmap(step_jac)(xc, uc, unc)  # (chunk, n, P + n)
        G = jax.vmap(read_jac)(xc)  # (chunk, p, P + n)
        Ft, Fx, Gt, Gx = F[..., :P], F[..., P:], G[..., :P], G[..., P:]

        def one(S, F):
            Fx_k, Ft_k = F
            return Fx_k @ S + Ft_k, S

        S_next, Sc = jax.lax.scan(one, S, (Fx, Ft))
        return S_next, Gx @ Sc + Gt

    S0 = jax.jacfwd(initial)(theta)  # (n, P)
    _, dy = jax.lax.scan(chunk, S0, (chunks(x), chunks(u), chunks(u_next)))
    return y, dy.reshape(-1, *dy.shape[2:])[:T]


def dataset_outputs_and_jacobian(params_to_model, theta, data):
    """`run_outputs_and_jacobian` of every run of a `Dataset`: readings (runs, T, p) and
    their Jacobian (runs, T, p, P)."""
    runs = jnp.arange(data.ts.shape[0])
    return jax.vmap(lambda ts, u, r: run_outputs_and_jacobian(params_to_model, theta, ts, u, r)
                    )(data.ts, data.inputs, runs)
