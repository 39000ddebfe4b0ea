"""`sensor_offset`: a constant offset in a sensor's reading (°C)."""

from __future__ import annotations

import numpy as np

from ._base import AbstractEffect, Term


class SensorOffset(AbstractEffect):
    kind = "sensor_offset"

    @property
    def is_term(self):
        return True

    def term(self, spec, effect, slot):
        return Term(self.kind, ("offset",), (False,), slot)

    def output(self, term, values):
        return 0.0, values[term.slot]

    def places(self, spec, columns):
        return [(c,) for c in spec.sensor_columns]

    def initial_parameters(self, spec, where):
        return {"offset": 0.0}

    def score_direction(self, ctx, where):
        d = np.zeros_like(ctx.y)
        d[..., ctx.sensor(where[0])] = 1.0
        return "output", [d]
