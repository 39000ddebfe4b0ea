"""`sensor_offset`: a constant offset in a sensor's reading (°C)."""

from __future__ import annotations

import numpy as np

from ._base import MAX_SENSOR_OFFSET, AbstractEffect, Term


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

    def unphysical(self, where, parameters, span):
        o = parameters.get("offset", 0.0)
        if abs(o) <= MAX_SENSOR_OFFSET:
            return None
        return (f"an offset of {o:+.3g} °C on {where[0]} is beyond any sensor's calibration "
                f"error (at most {MAX_SENSOR_OFFSET:g} °C is accepted): a wrong column, a "
                "wrong unit or a start the model does not match")
