"""`boundary`: an unmodelled second conduction path from a temperature input to a node."""

from __future__ import annotations

import numpy as np

from .._spec import Boundary as BoundaryEntry
from ._base import AbstractEffect, ParameterLink, param


class Boundary(AbstractEffect):
    kind = "boundary"

    def lower(self, spec, effect):
        col, node = effect.where
        hold = spec.hold_for(col, effect.hold)
        entry = BoundaryEntry(node, col, param(effect, "conductance", 0.01), hold)
        return (spec.replace(boundaries=spec.boundaries + (entry,)),
                [ParameterLink("conductance", f"boundaries.{node}-{col}.conductance")])

    def places(self, spec, columns):
        cols = [c for c, role in columns.items() if role != "power"]
        cols += [c for c in spec.boundary_columns if c not in cols]
        taken = {(b.input, b.node) for b in spec.boundaries}
        return [(c, n) for c in cols for n in spec.node_names if (c, n) not in taken]

    def initial_parameters(self, spec, where):
        g = min([b.conductance.value for b in spec.boundaries] or [0.1])
        return {"conductance": 0.1 * g}

    def score_direction(self, ctx, where):
        col, node = where
        i = ctx.node(node)
        w = np.zeros_like(ctx.T)
        w[..., i] = ctx.column(col) - ctx.T[..., i]
        return "heat", [w]
