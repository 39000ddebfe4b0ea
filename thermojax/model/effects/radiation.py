"""`radiation`: net radiative exchange `k (T_b⁴ − T_a⁴)` into `a`, temperatures in kelvin."""

from __future__ import annotations

import jax.numpy as jnp

from ._base import KELVIN, PathEffect


class Radiation(PathEffect):
    kind = "radiation"

    def heat(self, term, values, T, u, network):
        k = jnp.exp(values[term.slot])
        ta, tb = T[term.a] + KELVIN, self.far(term, T, u) + KELVIN
        return self.into_a(term, k * (tb ** 4 - ta ** 4), T)

    def initial_parameters(self, spec, where):
        # a radiative conductance 4 k T³ of a tenth of the path's, at 300 K
        return {"coefficient": 0.1 * self.path_value(spec, where) / (4 * 300.0 ** 3)}

    def score_direction(self, ctx, where):
        ta = ctx.T[..., ctx.node(where[0])] + KELVIN
        tb = ctx.temperature(where[1]) + KELVIN
        return "heat", [self.split(ctx, where, tb ** 4 - ta ** 4)]
