"""`sensor_gain`: a calibration slope error, reading `T + g (T − 25 °C)`."""

from __future__ import annotations

import numpy as np

from ._base import MAX_SENSOR_GAIN, T_REF, AbstractEffect, Term


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

    def unphysical(self, where, parameters, span):
        g = parameters.get("gain", 0.0)
        if abs(g) <= MAX_SENSOR_GAIN:
            return None
        return (f"a gain of {g:+.3g} means {where[0]} would read {1 + g:.0%} of its node's "
                f"temperature swing; a calibration slope error is a few percent (at most "
                f"{MAX_SENSOR_GAIN:.0%} is accepted), so the fit is explaining a thermal "
                "effect away")
