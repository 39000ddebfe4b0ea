"""`conductance_input`: a path whose conductance follows a measured input, `G0 (1 + c · input)`."""

from __future__ import annotations

from ._base import PathEffect


class ConductanceInput(PathEffect):
    kind = "conductance_input"

    def heat(self, term, values, T, u, network):
        c = values[term.slot]
        ta, tb = T[term.a], self.far(term, T, u)
        g0 = self.path_conductance(term, network)
        return self.into_a(term, g0 * c * u[term.column] * (tb - ta), T)

    def places(self, spec, columns):
        cols = [c for c, role in columns.items() if role != "temperature"]
        return [(*path, c) for path in super().places(spec, columns) for c in cols]

    def initial_parameters(self, spec, where):
        return {"coefficient": 0.0}

    def score_direction(self, ctx, where):
        ta = ctx.T[..., ctx.node(where[0])]
        tb = ctx.temperature(where[1])
        g0 = ctx.path_conductance(where)
        return "heat", [self.split(ctx, where, g0 * ctx.column(where[2]) * (tb - ta))]
