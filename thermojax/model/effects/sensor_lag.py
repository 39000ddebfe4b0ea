"""`sensor_lag`: a first-order lag between a node and its sensor's reading.

Lowered to a tiny fixed-capacitance node between the node and the sensor (a sensing
element of negligible mass: 1e-6 of the smallest capacitance), linked with
conductance `C/τ`. Its back-action on the node is 1e-6 of the node's own heat balance,
so the reading is the pure lag `dr/dt = (T − r)/τ` to that accuracy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._spec import Link, Node, Parameter
from ._base import AbstractEffect, ParameterLink, param, unique_name

RELATIVE_MASS = 1e-6


class SensorLag(AbstractEffect):
    kind = "sensor_lag"

    def lower(self, spec, effect):
        col = effect.where[0]
        i = spec.sensor_columns.index(col)
        sensor = spec.sensors[i]
        c = RELATIVE_MASS * min(n.capacitance.value for n in spec.nodes)
        tau = param(effect, "time_constant", 1.0)
        node = unique_name(spec, f"{col}_element")
        sensors = list(spec.sensors)
        sensors[i] = dataclasses.replace(sensor, node=node)
        lowered = spec.replace(
            nodes=spec.nodes + (Node(node, Parameter(c, True),
                                     process_noise=Parameter(0.0, True),
                                     added_by_effect=True),),
            links=spec.links + (Link((sensor.node, node), Parameter(c / tau.value, tau.fixed)),),
            sensors=tuple(sensors))
        return lowered, [ParameterLink("time_constant", f"links.{sensor.node}-{node}.conductance",
                                       scale=c, power=-1.0)]

    def places(self, spec, columns):
        return [(c,) for c in spec.sensor_columns]

    def initial_parameters(self, spec, where):
        return {"time_constant": 1.0}

    def direction_time_constant(self, ctx, j):
        return None if j == 0 else ctx.trial_time_constants()[j - 1]

    def with_time_constant(self, spec, where, params, tau):
        return {**params, "time_constant": float(tau)}

    def score_direction(self, ctx, where):
        # At τ → 0 the reading moves by −τ dT/dt; a lag of several samples is far from
        # that local direction (on building data the score test then misses a lag whose
        # likelihood ratio is in the thousands), so the lagged reading (lag(T, τ) − T)/τ
        # at the trial time constants is tried too, the best one scoring.
        s = ctx.sensor(where[0])
        T = ctx.T[..., ctx.sensor_node(s)]
        out = []
        for direction in [-ctx.dTdt[..., ctx.sensor_node(s)]] + [
                (ctx.lag(T, tau) - T) / tau for tau in ctx.trial_time_constants()]:
            d = np.zeros_like(ctx.y)
            d[..., s] = direction
            out.append(d)
        return "output", out
