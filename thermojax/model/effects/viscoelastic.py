"""`viscoelastic`: a strain state relaxing towards a node's temperature, adding
`k (T_node − ε)` to an inertial bias column. It lives in the bias channel (`_bias`),
not in the thermal model: the thermal fit never sees it."""

from __future__ import annotations

from ._base import AbstractEffect


class Viscoelastic(AbstractEffect):
    kind = "viscoelastic"

    def places(self, spec, columns):
        return [(n, b.column) for b in spec.biases for n in spec.node_names]

    def initial_parameters(self, spec, where):
        return {"time_constant": 600.0, "k": 0.0}
