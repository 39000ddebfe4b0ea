"""`conductance_temperature`: a path whose conductance is `G0 (1 + α (T̄ − 25 °C))`."""

from __future__ import annotations

from ._base import T_REF, PathEffect


class ConductanceTemperature(PathEffect):
    kind = "conductance_temperature"

    def heat(self, term, values, T, u, network):
        alpha = values[term.slot]
        ta, tb = T[term.a], self.far(term, T, u)
        g0 = self.path_conductance(term, network)
        return self.into_a(term, g0 * alpha * (0.5 * (ta + tb) - T_REF) * (tb - ta), T)

    def initial_parameters(self, spec, where):
        return {"alpha": 0.0}

    def score_direction(self, ctx, where):
        ta = ctx.T[..., ctx.node(where[0])]
        tb = ctx.temperature(where[1])
        g0 = ctx.path_conductance(where)
        return "heat", [self.split(ctx, where, g0 * (0.5 * (ta + tb) - T_REF) * (tb - ta))]
