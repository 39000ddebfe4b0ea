"""`conductance_temperature`: a path whose conductance is `G0 (1 + α (T̄ − 25 °C))`."""

from __future__ import annotations

from ._base import T_REF, ScaledPathEffect, factor_leaves_range


class ConductanceTemperature(ScaledPathEffect):
    kind = "conductance_temperature"

    def scale(self, term, values, ta, tb, u):
        return values[term.slot] * (0.5 * (ta + tb) - T_REF)

    def scale_direction(self, ctx, where, ta, tb):
        return 0.5 * (ta + tb) - T_REF

    def initial_parameters(self, spec, where):
        return {"alpha": 0.0}

    def unphysical(self, where, parameters, span):
        low, high = span.temperatures
        return factor_leaves_range(parameters.get("alpha", 0.0), low, high, T_REF,
                                   f"conductance {where[0]}–{where[1]}", "°C")
