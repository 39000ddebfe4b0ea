"""`capacitance_temperature`: a node whose capacitance is `C0 (1 + β (T − 25 °C))`.

Not an added heat flow but a rescaling of the node's rate, `dT/dt = f / (1 + β (T − 25))`
with `f` the rate the constant capacitance gives (`capacitance_factor`)."""

from __future__ import annotations

import numpy as np

from ._base import T_REF, AbstractEffect, Term, factor_leaves_range


class CapacitanceTemperature(AbstractEffect):
    kind = "capacitance_temperature"
    nonlinear = True

    @property
    def is_term(self):
        return True

    def term(self, spec, effect, slot):
        return Term(self.kind, ("beta",), (False,), slot,
                    a=spec.node_names.index(effect.where[0]))

    def capacitance_factor(self, term, values, T):
        """`(node, 1 + β (T − 25))`."""
        return term.a, 1.0 + values[term.slot] * (T[term.a] - T_REF)

    def places(self, spec, columns):
        return [(n,) for n in spec.node_names]

    def initial_parameters(self, spec, where):
        return {"beta": 0.0}

    def score_direction(self, ctx, where):
        a = ctx.node(where[0])
        w = np.zeros_like(ctx.T)
        w[..., a] = -ctx.capacitance[a] * (ctx.T[..., a] - T_REF) * ctx.dTdt[..., a]
        return "heat", [w]

    def unphysical(self, where, parameters, span):
        low, high = span.temperatures
        return factor_leaves_range(parameters.get("beta", 0.0), low, high, T_REF,
                                   f"capacitance of {where[0]}", "°C")
