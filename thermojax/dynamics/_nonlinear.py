"""Simulation of a model with nonlinear effects: exponential time differencing (ETD2).

`dx/dt = A x + B u(t) + N(x, u)`: the linear part is integrated exactly (as for a
linear model: stiff node time constants cost nothing), the small nonlinear rate `N`
(radiation, temperature-dependent conductance and capacitance, input-dependent
conductance) is taken linear in time over each sample interval, between its value
at the interval's start and a predicted value at its end (Cox & Matthews 2002,
ETD2RK), in `model.etd2_substeps` steps per sample period. Both integrals are the
first-order-hold input matrices of the system
`(A, I)`, so one matrix exponential of the augmented system gives every matrix:

    x̃       = Φ x_k + B0 u_k + B1 u_k+1 + (G0 + G1) N(x_k, u_k)
    x_k+1   = Φ x_k + B0 u_k + B1 u_k+1 + G0 N(x_k, u_k) + G1 N(x̃, u_k+1⁻)

(`u_k+1⁻`: a zero-order-hold input keeps its value `u_k` up to the interval's end).
The local error is third order in the sample period times the rate of change of `N`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._discretize import discretize, sample_period
from ..compilation._traced_cache import stored_jit
from ..model._system import LinearSystem


def _augmented(system: LinearSystem) -> LinearSystem:
    n = system.n_states
    return LinearSystem(system.A, jnp.concatenate([system.B, jnp.eye(n)], axis=1), system.C,
                        jnp.zeros((system.C.shape[0], system.B.shape[1] + n)),
                        holds=(*system.holds, *("foh",) * n), capacitance=system.capacitance)


def nonlinear_steady_state(model, system: LinearSystem, u0, iterations: int = 8):
    """The equilibrium (°C), shape (nodes,), of the nonlinear model at a constant input
    `u0` (inputs,), by Newton's method from the linear equilibrium."""
    x = system.steady_state(u0)

    def residual(x):
        return system.A @ x + system.B @ u0 + model.nonlinear_rate(system, x, u0)

    def newton(x, _):
        return x - jnp.linalg.solve(jax.jacfwd(residual)(x), residual(x)), None

    return jax.lax.scan(newton, x, None, length=iterations)[0]


def initial_state_nonlinear(model, system, u0, run_initial=None):
    """`model.initial_state` (°C, shape (nodes,)) from the nonlinear equilibrium."""
    return model.initial_state(system, u0, run_initial,
                               steady_state=functools.partial(nonlinear_steady_state, model))


def etd2_matrices(system: LinearSystem, dt, substeps: int):
    """`(Phi, B0, B1, G0, G1)` of one ETD2 step of `dt / substeps` (s): the exact-hold
    maps of the inputs (`B0`, `B1`) and of the nonlinear rate (`G0`, `G1`)."""
    m = system.B.shape[1]
    disc = discretize(_augmented(system), dt / substeps)
    return (disc.Phi, disc.B0[:, :m], disc.B1[:, :m], disc.B0[:, m:], disc.B1[:, m:])


def etd2_step(model, system: LinearSystem, dt, matrices=None, unroll: bool = True,
              substeps=None):
    """`step(x_k, u_k, u_k1) -> x_k+1` over one sample period `dt` (s), in
    `model.etd2_substeps` ETD2 steps with the inputs held as their `hold` says inside the
    period; `matrices`: `etd2_matrices` when already computed. `unroll`: the substeps
    written out (fastest in a sequential scan) or as a loop (less program to compile, for
    steps evaluated in bulk). `substeps`: another number of steps, possibly traced (a
    loop then, forward-differentiable only)."""
    if substeps is None:
        substeps = model.etd2_substeps
    unroll = unroll and isinstance(substeps, int)
    Phi, B0, B1, G0, G1 = etd2_matrices(system, dt, substeps) if matrices is None else matrices
    zoh = np.array([hold == "zoh" for hold in system.holds], dtype=bool)

    def one(x, u_a, u_b):
        u_end = jnp.where(zoh, u_a, u_b)
        linear = Phi @ x + B0 @ u_a + B1 @ u_b
        n_a = model.nonlinear_rate(system, x, u_a)
        x_pred = linear + (G0 + G1) @ n_a
        return linear + G0 @ n_a + G1 @ model.nonlinear_rate(system, x_pred, u_end)

    def step(x, u_k, u_k1):
        u_k1 = jnp.where(zoh, u_k, u_k1)  # a zero-order-hold input keeps u_k all period

        def substep(j, x):
            u_a = u_k + (j / substeps) * (u_k1 - u_k)
            u_b = u_k + ((j + 1) / substeps) * (u_k1 - u_k)
            return one(x, u_a, u_b)

        if unroll:
            for j in range(substeps):
                x = substep(j, x)
            return x
        return jax.lax.fori_loop(0, substeps, substep, x)

    return step


def simulate_run_nonlinear(model, system: LinearSystem, ts, u, x0):
    """States (T, n) of one run by ETD2 from `x0`; the sample period is the median step of `ts`."""
    step = etd2_step(model, system, sample_period(ts))
    u_next = jnp.concatenate([u[1:], u[-1:]], axis=0)
    return jax.lax.scan(lambda x, inp: (step(x, *inp), x), x0, (u, u_next))[1]


def dataset_states_nonlinear(model, data, run_initial=None):
    """Node temperatures (runs, T, n) of every run of a `Dataset`."""
    system = model.linear_system()

    def one(ts, u, r0):
        x0 = initial_state_nonlinear(model, system, u[0], r0)
        return simulate_run_nonlinear(model, system, ts, u, x0)

    return jax.vmap(one)(data.ts, data.inputs, run_initial)  # None: each run gets None


def readings(model, x):
    """The readings (..., p) of node temperatures `x` (..., n), °C: `C x + offset`."""
    offset = model.output_offset()
    return x @ model.linear_system().C.T + offset.reshape((1,) * (x.ndim - 1) + offset.shape)


def dataset_outputs_nonlinear(model, data, run_initial=None):
    """Free-run readings (runs, T, p) of every run."""
    return readings(model, dataset_states_nonlinear(model, data, run_initial))


@stored_jit(once=True)
def etd2_error(model, data, run_initial, substeps):
    """The estimated error (°C) of the model's readings simulated in `substeps` (traced:
    one program for every number) ETD2 steps per sample period: their largest difference,
    over runs, samples and outputs, from the same simulation in four times as many, times
    16/15 (ETD2's error falls as the square of the step, so the finer one's is a
    sixteenth of it). Both run in one scan."""
    system = model.linear_system()

    def one(ts, u, r0):
        dt = sample_period(ts)
        counts = (substeps, 4 * substeps)
        # both step counts' matrices in one batched computation (one copy to compile)
        mats = jax.vmap(lambda k: etd2_matrices(system, dt, k))(jnp.stack(counts))
        steps = tuple(etd2_step(model, system, dt, jax.tree.map(lambda a: a[i], mats),
                                unroll=False, substeps=k) for i, k in enumerate(counts))
        x0 = initial_state_nonlinear(model, system, u[0], r0)
        u_next = jnp.concatenate([u[1:], u[-1:]], axis=0)

        def body(xs, inp):
            xs = tuple(step(x, *inp) for step, x in zip(steps, xs))
            return xs, jnp.max(jnp.abs(system.C @ (xs[0] - xs[1])))

        return jnp.max(jax.lax.scan(body, (x0, x0), (u, u_next))[1])

    # run_initial None is an empty pytree: vmapped, each run gets None
    return (16 / 15) * jnp.max(jax.vmap(one)(data.ts, data.inputs, run_initial))
