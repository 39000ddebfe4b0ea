"""`heat_source`: a measured input column that also dissipates heat in a node, `q = g · input`."""

from __future__ import annotations

import numpy as np

from .._spec import HeatInput
from ._base import AbstractEffect, ParameterLink, param


class HeatSource(AbstractEffect):
    kind = "heat_source"

    def lower(self, spec, effect):
        col, node = effect.where
        hold = spec.hold_for(col, effect.hold)
        heat = HeatInput(node, col, param(effect, "gain", 0.1), hold)
        return (spec.replace(heat_inputs=spec.heat_inputs + (heat,)),
                [ParameterLink("gain", f"heat_inputs.{node}-{col}.gain")])

    def places(self, spec, columns):
        return [(c, n) for c, role in columns.items() if role != "temperature"
                for n in spec.node_names]

    def initial_parameters(self, spec, where):
        return {"gain": 0.1}

    def score_direction(self, ctx, where):
        col, node = where
        w = np.zeros_like(ctx.T)
        w[..., ctx.node(node)] = ctx.column(col)
        return "heat", [w]
