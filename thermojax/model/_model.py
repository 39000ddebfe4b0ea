"""A network together with what the likelihoods need: noise, process noise, initial state."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._network import ThermalNetwork
from ._spec import ModelSpec, Parameter

DEFAULT_NOISE = 0.01  # °C: start of an estimated sensor noise std without a value
DEFAULT_PROCESS_NOISE = 1e-3  # °C/√s: start of an estimated process noise without a value
DEFAULT_INITIAL_STD = 1.0  # °C
# ETD2 steps per sample period of a nonlinear simulation, unless a fit chose fewer
# (`fitting._integration`): fast nodes react within a sample to switched power.
DEFAULT_ETD2_SUBSTEPS = 4


class ThermalModel(eqx.Module):
    """The statistical model of a network's measurements.

    - `network`: the physics (`ThermalNetwork`).
    - `log_noise`: log of each sensor's measurement-noise std (°C).
    - `log_process_noise`: log of each node's diffusion std (°C/√s), Kalman only.
    - `initial`: initial temperature (°C) of the nodes in `initial_nodes`; the
      other nodes start at the steady state of the first input sample. (A fit gives
      every node of the file without `initial` a start from the data first:
      `fitting._initial_states`.)
    - `initial_std`: std of the initial state (°C), per node.
    - `etd2_substeps`: integration steps per sample period of a nonlinear model.
    """

    network: ThermalNetwork
    log_noise: Float[Array, " sensors"]
    log_process_noise: Float[Array, " nodes"]
    initial: Float[Array, " nodes"]
    initial_std: Float[Array, " nodes"]
    initial_nodes: tuple[int, ...] = eqx.field(static=True)
    # Term effects (offsets, gains, nonlinear heat flows): their parameters, logs where
    # positive, and their static descriptions (`effects.Term`); per term, the sensor it
    # reads into (NumPy bool, (sensors,); none for heat terms) is data, so that an offset
    # at another sensor is the same program.
    effect_values: Float[Array, " effect_parameters"] = None
    effect_terms: tuple = eqx.field(static=True, default=())
    effect_sensors: tuple = ()
    # True: every node's temperature is read out after the sensors (outputs: sensors,
    # then nodes), so one simulation gives the states that bias channels need.
    read_states: bool = eqx.field(static=True, default=False)
    # ETD2 steps per sample period when the model has nonlinear effects (`_nonlinear`).
    etd2_substeps: int = eqx.field(static=True, default=DEFAULT_ETD2_SUBSTEPS)
    # Nodes an effect added: they start at rest given every other node's start.
    added_nodes: tuple[int, ...] = eqx.field(static=True, default=())

    @classmethod
    def from_spec(cls, spec: ModelSpec) -> "ThermalModel":
        """Build from a model file's values. Structural effects must have been lowered
        (`effects.lower_effects`); this lowers them if not."""
        from .effects import KINDS, lower_effects

        if any(not KINDS[e.kind].is_term and e.kind != "viscoelastic" for e in spec.effects):
            spec = lower_effects(spec).spec
        noise = [s.noise.value if s.noise is not None else DEFAULT_NOISE for s in spec.sensors]
        q = [n.process_noise.value if n.process_noise is not None else DEFAULT_PROCESS_NOISE
             for n in spec.nodes]
        q = [max(v, 1e-12) for v in q]  # a fixed zero process noise is log(1e-12): negligible
        init = [n.initial.value if n.initial is not None else 0.0 for n in spec.nodes]
        std = [n.initial_std if n.initial_std is not None else DEFAULT_INITIAL_STD
               for n in spec.nodes]
        terms, sensors, values = [], [], []
        for e in term_effects(spec):
            kind = KINDS[e.kind]
            term = kind.term(spec, e, len(values))
            sensors.append(np.array([c == e.where[0] for c in spec.sensor_columns]))
            first = kind.initial_parameters(spec, e.where) if set(e.parameters) != set(
                term.parameters) else {}
            for name, log in zip(term.parameters, term.logs):
                v = e.parameters[name].value if name in e.parameters else first[name]
                values.append(float(np.log(v)) if log else float(v))
            terms.append(term)
        return cls(ThermalNetwork.from_spec(spec),
                   *jax.device_put((np.log(np.asarray(noise, float)), np.log(np.asarray(q, float)),
                                    np.asarray(init, float), np.asarray(std, float))),
                   tuple(i for i, n in enumerate(spec.nodes) if n.initial is not None),
                   jax.device_put(np.asarray(values, float).reshape(-1)), tuple(terms),
                   tuple(sensors),
                   added_nodes=tuple(i for i, n in enumerate(spec.nodes) if n.added_by_effect))

    @property
    def is_nonlinear(self) -> bool:
        from .effects import KINDS

        return any(KINDS[t.kind].nonlinear for t in self.effect_terms)

    def effect_parameter_values(self) -> list[float]:
        """Physical values of `effect_values`, in term order."""
        v = np.asarray(self.effect_values)
        out = []
        for t in self.effect_terms:
            for j, log in enumerate(t.logs):
                out.append(float(np.exp(v[t.slot + j])) if log else float(v[t.slot + j]))
        return out

    def _output_affine(self):
        """Per-sensor `(scale, offset)` of the readings: `y = scale · T + offset`."""
        from .effects import KINDS

        p = len(self.network.topology.sensor_nodes)
        scale, offset = jnp.ones(p), jnp.zeros(p)
        for t, sensor in zip(self.effect_terms, self.effect_sensors):
            got = KINDS[t.kind].output(t, self.effect_values)
            if got is not None:
                sensor = sensor.astype(scale.dtype)
                scale, offset = scale + got[0] * sensor, offset + got[1] * sensor
        return scale, offset

    def output_offset(self) -> Float[Array, " outputs"]:
        """Constant added to every reading (°C): sensor offsets and gain terms (zero for
        the node read-outs of `read_states`)."""
        offset = self._output_affine()[1]
        if self.read_states:
            offset = jnp.concatenate([offset, jnp.zeros(self.network.log_capacitance.shape[0])])
        return offset

    def linear_system(self):
        """The network's linear system with the sensors' gains in its output matrix (and
        every node's temperature as further outputs under `read_states`)."""
        system = self.network.linear_system()
        if self.effect_terms:
            scale = self._output_affine()[0]
            system = eqx.tree_at(lambda s: s.C, system, system.C * scale[:, None])
        if self.read_states:
            n, m = system.B.shape
            system = eqx.tree_at(lambda s: (s.C, s.D), system, (
                jnp.concatenate([system.C, jnp.eye(n, dtype=system.C.dtype)]),
                jnp.concatenate([system.D, jnp.zeros((n, m), system.D.dtype)])))
        return system

    def nonlinear_rate(self, system, x, u) -> Float[Array, " nodes"]:
        """`N(x, u)` (°C/s): the nonlinear terms' part of `dx/dt = A x + B u + N(x, u)`."""
        from .effects import KINDS

        net = self.network
        heat = jnp.zeros_like(x)
        factors = []
        for t in self.effect_terms:
            kind = KINDS[t.kind]
            h = kind.heat(t, self.effect_values, x, u, net)
            if h is not None:
                heat = heat + h
            if hasattr(kind, "capacitance_factor"):
                factors.append(kind.capacitance_factor(t, self.effect_values, x))
        rate = heat / system.capacitance
        for i, s in factors:
            # node i's whole rate f_i = (A x + B u)_i + rate_i becomes f_i / s; applied in
            # turn, factors on one node multiply. One row of A and B as a single dot (two
            # small dots, or the whole matrices, run 3-5x slower in XLA's loop on CPU).
            f_i = jnp.concatenate([system.A[i], system.B[i]]) @ jnp.concatenate([x, u]) + rate[i]
            rate = rate + np.eye(rate.shape[0])[i] * (f_i * (1.0 / s - 1.0))
        return rate

    @property
    def noise(self) -> Float[Array, " sensors"]:
        return jnp.exp(self.log_noise)

    @property
    def process_noise(self) -> Float[Array, " nodes"]:
        return jnp.exp(self.log_process_noise)

    def initial_state(self, system, u0, run_initial=None, steady_state=None, solve=None
                      ) -> Float[Array, " nodes"]:
        """The initial state x0 (°C) of a run.

        The nodes in `initial_nodes` start at `initial` (or this run's estimate), the
        nodes an effect added (`added_nodes`) where the linear part is at rest given every
        other node's start, and the rest at the equilibrium `x_ss` of the first input
        sample. With `f` the added nodes and `o` the others, `x_f = x_ss,f + δ_f` solving
        `A_ff δ_f = −A_fo (x_o − x_ss,o)`: an unmodelled mass between a room that starts
        warm and the outdoors starts between them, not at the outdoors' equilibrium.

        **Arguments:**

        - `system`: the model's `LinearSystem` (`self.linear_system()`).
        - `u0`: the run's first input sample, shape (inputs,).
        - `run_initial`: this run's initial temperatures (°C), one per entry of
          `initial_nodes`; default `initial`.
        - `steady_state`: `(system, u0) -> x`, the equilibrium solve; default
          `system.steady_state`. The fit's sensitivities pass a small Gauss-Jordan solve,
          a nonlinear model its Newton iteration (`dynamics._nonlinear`).
        - `solve`: `(M, b) -> x` for the added nodes' small system; default
          `jnp.linalg.solve`.

        **Returns:** x0, shape (nodes,).
        """
        x0 = system.steady_state(u0) if steady_state is None else steady_state(system, u0)
        if not self.initial_nodes:
            return x0
        idx = np.array(self.initial_nodes)
        values = self.initial[idx] if run_initial is None else run_initial
        delta = jnp.zeros_like(x0).at[idx].set(values - x0[idx])
        if self.added_nodes:
            f = np.array(self.added_nodes)
            # rows scaled by the capacitances: the conductance matrix, symmetric
            c = (system.capacitance[f] if system.capacitance is not None
                 else jnp.ones(f.size, x0.dtype))[:, None]
            M, rhs = -c * system.A[np.ix_(f, f)], (c * system.A[f]) @ delta
            delta = delta.at[f].set(jnp.linalg.solve(M, rhs) if solve is None
                                    else solve(M, rhs))
        return x0 + delta


def model_to_spec(model: ThermalModel, spec: ModelSpec, process_noise: bool = False) -> ModelSpec:
    """Write a model's values back into its spec (fixed flags and structure kept).

    With `process_noise` (a Kalman fit, which estimates it), every node's process noise is
    written, also where the spec left it out; otherwise only where the spec has it."""
    net = model.network

    def values(log_values):  # physical values, in NumPy (no eager XLA programs)
        return np.exp(np.asarray(log_values))

    def upd(p: Parameter | None, v) -> Parameter:
        return Parameter(float(v), p.fixed if p is not None else False)

    nodes = tuple(dataclasses.replace(
        n, capacitance=upd(n.capacitance, c),
        process_noise=upd(n.process_noise, q) if process_noise or n.process_noise is not None
        else None)
        for n, c, q in zip(spec.nodes, values(net.log_capacitance), values(model.log_process_noise)))
    links = tuple(dataclasses.replace(k, conductance=upd(k.conductance, g))
                  for k, g in zip(spec.links, values(net.log_conductance)))
    bounds = tuple(dataclasses.replace(b, conductance=upd(b.conductance, g))
                   for b, g in zip(spec.boundaries, values(net.log_boundary_conductance)))
    heats = tuple(dataclasses.replace(h, gain=upd(h.gain, g))
                  for h, g in zip(spec.heat_inputs, values(net.log_heat_gain)))
    sensors = tuple(dataclasses.replace(s, noise=upd(s.noise, sd))
                    for s, sd in zip(spec.sensors, values(model.log_noise)))
    values = iter(model.effect_parameter_values())
    by_effect = {id(e): t for e, t in zip(term_effects(spec), model.effect_terms, strict=True)}
    effects = []
    for e in spec.effects:
        term = by_effect.get(id(e))
        if term is not None:
            e = dataclasses.replace(e, parameters={
                **e.parameters, **{p: upd(e.parameters.get(p), next(values))
                                   for p in term.parameters}})
        effects.append(e)
    return spec.replace(nodes=nodes, links=links, boundaries=bounds, heat_inputs=heats,
                        sensors=sensors, effects=tuple(effects))


def term_effects(spec: ModelSpec) -> list:
    """The effects of `spec` that a model holds as terms (`ThermalModel.effect_terms`),
    in its order."""
    from .effects import KINDS

    return [e for e in spec.effects if KINDS[e.kind].is_term]
