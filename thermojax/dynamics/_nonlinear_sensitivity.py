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
4. the readings `y = C x + offset` have the sensitivities `C S_k + C' x_k + offset'`.

The products are the same as `jax.jacfwd`'s, so the result equals it to roundoff
(tests/test_nonlinear_sensitivity.py). Chunks of `_CHUNK` samples bound the memory of
the per-sample derivatives to (chunk, n, n + P) per run; the step is differentiated
along the states and along the parameters separately (no zero tangents pushed).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._discretize import sample_period
from ._nonlinear import (etd2_matrices, etd2_step, initial_state_nonlinear,
                         simulate_run_nonlinear)

_CHUNK = 128  # samples differentiated in one vectorized pass (64: 6 % slower on imu6)


def run_outputs_and_jacobian(params_to_model, theta, ts, u, run: int | jax.Array, x=None):
    """Free-run readings (T, p) of one run of a nonlinear model and their Jacobian in
    `theta` (T, p, P).

    `params_to_model(theta) -> (model, run_initial)`, `run_initial` (runs, k) or None;
    `ts` (T,) s, `u` (T, m) the run's inputs, `run` its index in `run_initial`; `x` (T, n)
    its states at `theta` when already simulated.
    """

    def parts(t):
        model, run_initial = params_to_model(t)
        return model, model.linear_system(), None if run_initial is None else run_initial[run]

    def initial(t):
        model, system, r0 = parts(t)
        return initial_state_nonlinear(model, system, u[0], r0)

    dt = sample_period(ts)
    eye = jnp.eye(theta.shape[0], dtype=theta.dtype)

    # What depends on the parameters alone (step matrices, read-out, the model's own
    # arrays), with its tangents along every parameter, once per run: the per-sample
    # step below is differentiated along these, not through the model's construction.
    model, system, _ = parts(theta)
    static = eqx.partition((model, system), eqx.is_inexact_array)[1]

    def small(t):
        model, system, _ = parts(t)
        return (etd2_matrices(system, dt, model.etd2_substeps), system.C,
                model.output_offset(), eqx.filter((model, system), eqx.is_inexact_array))

    (mats, C, offset, arrays), (dmats, dC, doffset, darrays) = jax.vmap(
        lambda v: jax.jvp(small, (theta,), (v,)), out_axes=(None, 0))(eye)

    def step(arrays, matrices, x, u_k, u_k1):
        model, system = eqx.combine(arrays, static)
        # substeps as a loop: this step is evaluated in bulk, and an unrolled one would
        # make the fit's program half as large again to compile
        return etd2_step(model, system, dt, matrices=matrices, unroll=False)(x, u_k, u_k1)

    if x is None:
        x = simulate_run_nonlinear(model, system, ts, u, initial(theta))  # (T, n)
    y = x @ C.T + offset[None, :]

    def step_jacobians(xk, uk, uk1):  # dF/dx (n, n) and dF/dθ (n, P) at one sample
        along_x = jax.vmap(lambda d: jax.jvp(lambda x_: step(arrays, mats, x_, uk, uk1),
                                             (xk,), (d,))[1])
        along_t = jax.vmap(lambda da, dm: jax.jvp(lambda a, m: step(a, m, xk, uk, uk1),
                                                   (arrays, mats), (da, dm))[1])
        return along_x(jnp.eye(xk.shape[0], dtype=xk.dtype)).T, along_t(darrays, dmats).T

    def chunk(S, inp):
        Fx, Ft = jax.vmap(step_jacobians)(*inp)  # (chunk, n, n), (chunk, n, P)

        def one(S, F):
            return F[0] @ S + F[1], S

        return jax.lax.scan(one, S, (Fx, Ft))

    T = x.shape[0]
    pad = -T % _CHUNK

    def chunks(a):  # (T, ...) -> (T / chunk, chunk, ...), padded with the last sample
        a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)], axis=0)
        return a.reshape(-1, _CHUNK, *a.shape[1:])

    u_next = jnp.concatenate([u[1:], u[-1:]], axis=0)
    S0 = jax.jacfwd(initial)(theta)  # (n, P)
    _, S = jax.lax.scan(chunk, S0, (chunks(x), chunks(u), chunks(u_next)))
    S = S.reshape(-1, *S.shape[2:])[:T]  # (T, n, P)
    # y = C x + offset: dy = C S + dC x + d offset
    dy = jnp.einsum("pn,tnq->tpq", C, S) + jnp.einsum("qpn,tn->tpq", dC, x) + doffset.T[None]
    return y, dy


def dataset_outputs_and_jacobian(params_to_model, theta, data, states=None):
    """`run_outputs_and_jacobian` of every run of a `Dataset`: readings (runs, T, p) and
    their Jacobian (runs, T, p, P); `states` (runs, T, n) when already simulated."""
    runs = jnp.arange(data.ts.shape[0])
    return jax.vmap(lambda ts, u, r, x: run_outputs_and_jacobian(  # states None: x None
        params_to_model, theta, ts, u, r, x))(data.ts, data.inputs, runs, states)
