"""`sensor_gain`: a calibration slope error, reading `T + g (T − 25 °C)`."""

from __future__ import annotations

import numpy as np

from ._base import T_REF, AbstractEffect, Term


class SensorGain(AbstractEffect):
    kind = "sensor_gain"

    @property
    def is_term(self):
        return True

    def term(self, spec, effect, slot):
        return Term(self.kind, ("gain",), (False,), slot)

    def output(self, term, values):
        g = values[term.slot]
        return g, -T_REF * g  # added to the reading's scale (1 + g) and offset

    def places(self, spec, columns):
        return [(c,) for c in spec.sensor_columns]

    def initial_parameters(self, spec, where):
        return {"gain": 0.0}

    def score_direction(self, ctx, where):
        d = np.zeros_like(ctx.y)
        s = ctx.sensor(where[0])
        d[..., s] = ctx.T[..., ctx.sensor_node(s)] - T_REF
        return "output", [d]
