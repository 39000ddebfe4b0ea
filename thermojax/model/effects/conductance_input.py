"""`conductance_input`: a path whose conductance follows a measured input, `G0 (1 + c · input)`."""

from __future__ import annotations

from ._base import ScaledPathEffect, factor_leaves_range


class ConductanceInput(ScaledPathEffect):
    kind = "conductance_input"

    def scale(self, term, values, ta, tb, u):
        return values[term.slot] * u[term.column]

    def scale_direction(self, ctx, where, ta, tb):
        return ctx.column(where[2])

    def places(self, spec, columns):
        cols = [c for c, role in columns.items() if role != "temperature"]
        return [(*path, c) for path in super().places(spec, columns) for c in cols]

    def initial_parameters(self, spec, where):
        return {"coefficient": 0.0}

    def unphysical(self, where, parameters, span):
        if where[-1] not in span.columns:
            return None
        low, high = span.columns[where[-1]]
        return factor_leaves_range(parameters.get("coefficient", 0.0), low, high, 0.0,
                                   f"conductance {where[0]}–{where[1]}", f"({where[-1]})")
