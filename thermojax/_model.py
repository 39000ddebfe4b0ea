"""A network together with what the likelihoods need: noise, process noise, initial state."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._network import ThermalNetwork
from ._spec import ModelSpec, Parameter

DEFAULT_NOISE = 0.01  # °C: start of an estimated sensor noise std without a value
DEFAULT_PROCESS_NOISE = 1e-3  # °C/√s: start of an estimated process noise without a value
DEFAULT_INITIAL_STD = 1.0  # °C


class ThermalModel(eqx.Module):
    """The statistical model of a network's measurements.

    - `network`: the physics (`ThermalNetwork`).
    - `log_noise`: log of each sensor's measurement-noise std (°C).
    - `log_process_noise`: log of each node's diffusion std (°C/√s), Kalman only.
    - `initial`: initial temperature (°C) of the nodes in `initial_nodes`; the
      other nodes start at the steady state of the first input sample.
    - `initial_std`: std of the initial state (°C), per node.
    """

    network: ThermalNetwork
    log_noise: Float[Array, " sensors"]
    log_process_noise: Float[Array, " nodes"]
    initial: Float[Array, " nodes"]
    initial_std: Float[Array, " nodes"]
    initial_nodes: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    def from_spec(cls, spec: ModelSpec) -> "ThermalModel":
        noise = [s.noise.value if s.noise is not None else DEFAULT_NOISE for s in spec.sensors]
        q = [n.process_noise.value if n.process_noise is not None else DEFAULT_PROCESS_NOISE
             for n in spec.nodes]
        q = [max(v, 1e-12) for v in q]  # a fixed zero process noise is log(1e-12): negligible
        init = [n.initial.value if n.initial is not None else 0.0 for n in spec.nodes]
        std = [n.initial_std if n.initial_std is not None else DEFAULT_INITIAL_STD
               for n in spec.nodes]
        return cls(ThermalNetwork.from_spec(spec), jnp.log(jnp.asarray(noise, float)),
                   jnp.log(jnp.asarray(q, float)), jnp.asarray(init, float),
                   jnp.asarray(std, float),
                   tuple(i for i, n in enumerate(spec.nodes) if n.initial is not None))

    @property
    def noise(self) -> Float[Array, " sensors"]:
        return jnp.exp(self.log_noise)

    @property
    def process_noise(self) -> Float[Array, " nodes"]:
        return jnp.exp(self.log_process_noise)

    def initial_state(self, system, u0, run_initial=None) -> Float[Array, " nodes"]:
        """x0: steady state at `u0`, with `initial_nodes` set to `initial` (or to this
        run's estimate `run_initial`, one value per entry of `initial_nodes`)."""
        x0 = system.steady_state(u0)
        if self.initial_nodes:
            idx = np.array(self.initial_nodes)
            values = self.initial[idx] if run_initial is None else run_initial
            x0 = x0.at[idx].set(values)
        return x0


def model_to_spec(model: ThermalModel, spec: ModelSpec, process_noise: bool = False) -> ModelSpec:
    """Write a model's values back into its spec (fixed flags and structure kept).

    With `process_noise` (a Kalman fit, which estimates it), every node's process noise is
    written, also where the spec left it out; otherwise only where the spec has it."""
    net = model.network

    def upd(p: Parameter | None, v) -> Parameter:
        return Parameter(float(v), p.fixed if p is not None else False)

    nodes = tuple(dataclasses.replace(
        n, capacitance=upd(n.capacitance, c),
        process_noise=upd(n.process_noise, q) if process_noise or n.process_noise is not None
        else None)
        for n, c, q in zip(spec.nodes, np.asarray(net.capacitance), np.asarray(model.process_noise)))
    links = tuple(dataclasses.replace(k, conductance=upd(k.conductance, g))
                  for k, g in zip(spec.links, np.asarray(net.conductance)))
    bounds = tuple(dataclasses.replace(b, conductance=upd(b.conductance, g))
                   for b, g in zip(spec.boundaries, np.asarray(net.boundary_conductance)))
    heats = tuple(dataclasses.replace(h, gain=upd(h.gain, g))
                  for h, g in zip(spec.heat_inputs, np.asarray(net.heat_gain)))
    sensors = tuple(dataclasses.replace(s, noise=upd(s.noise, sd))
                    for s, sd in zip(spec.sensors, np.asarray(model.noise)))
    return spec.replace(nodes=nodes, links=links, boundaries=bounds, heat_inputs=heats,
                        sensors=sensors)
