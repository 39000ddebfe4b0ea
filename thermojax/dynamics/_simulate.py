"""Simulation of a system through sampled inputs: exact hold (scan or associative scan) or diffrax."""

from __future__ import annotations

import abc

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._blocked import block_maps, block_rows
from ._discretize import (AbstractDiscretization, MatrixExponential, discretize, modal_decomposition,
                          sample_period)
from ..model._system import LinearSystem


class Solution(eqx.Module):
    """A simulated trajectory: `ts` (s), `states` (°C for node temperatures), `outputs`."""

    ts: Float[Array, " times"]
    states: Float[Array, "times states"]
    outputs: Float[Array, "times outputs"]


def as_system(model) -> LinearSystem | eqx.Module:
    """Accept a `ThermalNetwork` (or anything with `.linear_system()`) or a system."""
    return model.linear_system() if hasattr(model, "linear_system") else model


class AbstractSimulator(eqx.Module):
    """How to integrate a system through sampled inputs."""

    @abc.abstractmethod
    def run(self, system, x0: Float[Array, " states"], inputs: Float[Array, "times inputs"],
            ts: Float[Array, " times"]) -> Solution:
        ...


def simulate(model, inputs: Float[Array, "times inputs"], ts: Float[Array, " times"],
             x0: Float[Array, " states"] | None = None,
             simulator: AbstractSimulator | None = None) -> Solution:
    """Simulate one experiment.

    **Arguments:**

    - `model`: a `ThermalNetwork`, a `LinearSystem`, or (for `DiffraxSimulator`)
      any module with `vector_field(t, x, u)` and `observe(x, u)`.
    - `inputs`: the sampled inputs, one row per time, columns in the model's
      input order (°C for boundary temperatures, W for heat inputs).
    - `ts`: sample times (s), uniformly spaced for `ExactHold`.
    - `x0`: initial state; default the steady state at the first input sample.
    - `simulator`: default `ExactHold()`.

    **Returns:** a `Solution` with one row per sample time.

    Batch over experiments with `jax.vmap`, or with `simulate_batch` for runs
    of different lengths.
    """
    system = as_system(model)
    simulator = ExactHold() if simulator is None else simulator
    inputs = jnp.asarray(inputs)
    ts = jnp.asarray(ts)
    if inputs.ndim != 2 or ts.ndim != 1 or inputs.shape[0] != ts.shape[0]:
        raise ValueError(f"`simulate(inputs, ts)` needs inputs of shape (times, inputs) and ts of "
                         f"shape (times,), got {inputs.shape} and {ts.shape}.")
    if x0 is None:
        x0 = steady_state(system, inputs[0])
    return simulator.run(system, jnp.asarray(x0), inputs, ts)


def steady_state(system, u: Float[Array, " inputs"]) -> Float[Array, " states"]:
    """Equilibrium state for a constant input `u` (the system's own `steady_state`)."""
    return system.steady_state(u)


class ExactHold(AbstractSimulator):
    """Exact sampled simulation of a `LinearSystem`, each input held as its `hold` says.

    Discretizes once with `discretization` and runs the recurrence
    `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]`: blocked (`parallel=False`: blocks
    of 16 samples evaluated together by matrix products, only the block starts
    sequential, through a short `lax.scan`; fast on CPU and under `jax.vmap`) or
    with `lax.associative_scan` (`parallel=True`: O(log T) depth, for long
    horizons on accelerators; on a reciprocal network it runs diagonally in
    modal coordinates). Both equal the step-by-step recurrence to float64
    roundoff. `ts` must be uniformly spaced; the period is their median step.
    """

    discretization: AbstractDiscretization = MatrixExponential()
    parallel: bool = eqx.field(static=True, default=False)

    def run(self, system, x0, inputs, ts) -> Solution:
        if not isinstance(system, LinearSystem):
            raise TypeError("`ExactHold` simulates linear systems only; use "
                            "`DiffraxSimulator()` for a nonlinear model.")
        dt = sample_period(ts)  # the median step: jitter on one step does not set it
        disc = discretize(system, dt, self.discretization)
        if self.parallel:
            drive = inputs[:-1] @ disc.B0.T + inputs[1:] @ disc.B1.T  # (times-1, states)
            states = _associative_states(system, disc, x0, drive)
            outputs = states @ disc.C.T + inputs @ disc.D.T
        else:
            states, outputs = _blocked_hold(disc, x0, inputs)
        return Solution(ts, states, outputs)


def _blocked_hold(disc, x0, inputs):
    """States (times, n) and outputs (times, p) of the exact-hold recurrence, blocked
    (`_blocked`). Under `jax.jit`, using only the outputs lets XLA drop the product that
    forms the states."""
    Phi, B0, B1, C, D = disc.Phi, disc.B0, disc.B1, disc.C, disc.D
    dtype = jnp.result_type(Phi, inputs, x0)
    u = inputs.astype(dtype)
    x0 = x0.astype(dtype)
    T = u.shape[0]
    n, m = B0.shape
    states_readout = (jnp.eye(n, dtype=dtype), jnp.zeros((n, m), dtype))
    DL, N, (state_map, output_map) = block_maps(Phi, B0, B1, (states_readout, (C, D)))
    w = block_rows(DL, N, x0 - B1 @ u[0], u)
    states = (w @ state_map.T).reshape(-1, n)
    # rows by the states' count, not -1: a model without sensors has outputs (times, 0)
    outputs = (w @ output_map.T).reshape(states.shape[0], C.shape[0])[:T]
    states = states[:T].at[0].set(x0)  # x0 exactly, not z0 + B1 u0
    return states, outputs


def _associative_states(system: LinearSystem, disc, x0, drive):
    """All states of `x[k+1] = Phi x[k] + b[k]` by a parallel prefix over affine maps."""
    if system.capacitance is not None:
        # Diagonal in modal coordinates z = Q x: z[k+1] = e^{-λ dt} z[k] + Q b[k].
        lam, P, Q = modal_decomposition(system)
        decay = jnp.exp(-lam * disc.dt)
        zb = drive @ Q.T
        a = jnp.broadcast_to(decay, zb.shape)
        a = jnp.concatenate([jnp.zeros_like(decay)[None], a], axis=0)
        zb = jnp.concatenate([(Q @ x0)[None], zb], axis=0)

        def combine(left, right):
            a1, b1 = left
            a2, b2 = right
            return a1 * a2, a2 * b1 + b2

        _, z = jax.lax.associative_scan(combine, (a, zb))
        return z @ P.T
    n = x0.shape[0]
    A = jnp.broadcast_to(disc.Phi, (drive.shape[0], n, n))
    A = jnp.concatenate([jnp.zeros((1, n, n)), A], axis=0)
    b = jnp.concatenate([x0[None], drive], axis=0)

    def combine_dense(left, right):
        A1, b1 = left
        A2, b2 = right
        return A2 @ A1, jnp.einsum("...ij,...j->...i", A2, b1) + b2

    _, states = jax.lax.associative_scan(combine_dense, (A, b))
    return states


class DiffraxSimulator(AbstractSimulator):
    """Integrate `dx/dt = f(t, x, u(t))` with diffrax, for nonlinear right-hand sides.

    Inputs move between samples as their holds say (linear, or held constant).
    Each sample interval `[t_k, t_k+1]` is its own `diffeqsolve`, on which the
    input is the interval's own segment, a smooth function of `t`: `u[k]`
    (zero-order hold) or `u[k] + (t - t_k)/(t_k+1 - t_k) (u[k+1] - u[k])`
    (first-order hold, extended linearly past the interval's ends). So no kink
    or jump of the input is ever seen inside a step, not even by stages that
    fall outside the step (`Kvaerno5` evaluates one at 1.23 steps), nor by the
    stage at the step's end. The default solver `Kvaerno5` is implicit
    (L-stable), for stiff networks. `max_steps` bounds each interval's solve.
    """

    solver: diffrax.AbstractSolver = diffrax.Kvaerno5()
    rtol: float = 1e-8
    atol: float = 1e-8
    max_steps: int = eqx.field(static=True, default=1_000_000)

    def run(self, system, x0, inputs, ts) -> Solution:
        holds = getattr(system, "holds", None)
        if holds is None:
            raise TypeError("`DiffraxSimulator` needs a system with `holds` (one per input).")
        zoh = jnp.array([h == "zoh" for h in holds])

        def f(t, x, args):
            t0, dt, u0, u1 = args
            u = jnp.where(zoh, u0, u0 + ((t - t0) / dt) * (u1 - u0))
            return system.vector_field(t, x, u)

        term = diffrax.ODETerm(f)
        controller = diffrax.PIDController(rtol=self.rtol, atol=self.atol)

        def interval(x, segment):
            t0, t1, u0, u1 = segment
            sol = diffrax.diffeqsolve(term, self.solver, t0=t0, t1=t1, dt0=t1 - t0, y0=x,
                                      args=(t0, t1 - t0, u0, u1), stepsize_controller=controller,
                                      max_steps=self.max_steps)
            return sol.ys[-1], sol.ys[-1]

        _, rest = jax.lax.scan(interval, x0, (ts[:-1], ts[1:], inputs[:-1], inputs[1:]))
        states = jnp.concatenate([x0[None, :], rest], axis=0)
        # Outputs see the sampled input, not the interpolant's left limit.
        outputs = jax.vmap(system.observe)(states, inputs)
        return Solution(ts, states, outputs)


def simulate_batch(model, experiments, simulator: AbstractSimulator | None = None,
                   x0s=None) -> list[Solution]:
    """Simulate several experiments of different lengths in one vmapped call.

    **Arguments:**

    - `model`: as for `simulate`.
    - `experiments`: a sequence of `(inputs, ts)` pairs, `inputs` of shape
      (times_i, inputs), each with its own uniform sample period.
    - `x0s`: optional sequence of initial states (None entries: steady state).

    **Returns:** one `Solution` per experiment, trimmed to its own length.

    Runs are padded to the longest by holding their last input (which leaves
    the real samples untouched, since a step only looks forward), simulated
    under `jax.vmap`, and trimmed.
    """
    system = as_system(model)
    lengths = [int(jnp.shape(u)[0]) for u, _ in experiments]
    longest = max(lengths)
    if min(lengths) < 2:
        raise ValueError("`simulate_batch` needs at least two samples per experiment.")
    us, tss, x0_list = [], [], []
    for i, (u, ts) in enumerate(experiments):
        u, ts = jnp.asarray(u), jnp.asarray(ts)
        pad = longest - u.shape[0]
        dt = sample_period(ts)
        us.append(jnp.concatenate([u, jnp.broadcast_to(u[-1], (pad, u.shape[1]))]))
        tss.append(jnp.concatenate([ts, ts[-1] + dt * jnp.arange(1, pad + 1)]))
        x0 = None if x0s is None else x0s[i]
        x0_list.append(steady_state(system, u[0]) if x0 is None else jnp.asarray(x0))
    batched = _simulate_padded(system, jnp.stack(us), jnp.stack(tss), jnp.stack(x0_list),
                               ExactHold() if simulator is None else simulator)
    return [Solution(batched.ts[i, :n], batched.states[i, :n], batched.outputs[i, :n])
            for i, n in enumerate(lengths)]


@eqx.filter_jit
def _simulate_padded(system, us, tss, x0s, simulator):
    return jax.vmap(lambda u, ts, x0: simulator.run(system, x0, u, ts))(us, tss, x0s)
