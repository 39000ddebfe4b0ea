"""`heat_source`: a measured input column that also dissipates heat in a node, `q = g · input`.

The column may be one the model does not use yet, or a heat input it already routes to
other nodes (solar radiation that heats the interior may heat the envelope too:
Bacher & Madsen's `Ae`)."""

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

    def held_by(self, spec, where):
        return tuple(where) in _heated(spec)

    def places(self, spec, columns):
        heated = _heated(spec)
        routed = list(dict.fromkeys(h.input for h in spec.heat_inputs))
        unused = [c for c, role in columns.items() if role != "temperature"]
        return [(c, n) for c in unused + routed for n in spec.node_names
                if (c, n) not in heated]

    def initial_parameters(self, spec, where):
        return {"gain": 0.1}

    def score_direction(self, ctx, where):
        col, node = where
        w = np.zeros_like(ctx.T)
        w[..., ctx.node(node)] = ctx.column(col)
        return "heat", [w]


def _heated(spec) -> set[tuple[str, str]]:
    """`(column, node)` of every heat input of `spec`."""
    return {(h.input, h.node) for h in spec.heat_inputs}
