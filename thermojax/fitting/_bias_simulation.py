"""The bias columns (docs/formats.md §4) of a model simulated as written: each
`[[biases]]` entry's fitted coefficients applied to the simulated node temperatures and
the model's own state derivatives, so `simulate` writes every column `fit` predicts."""

from __future__ import annotations

import numpy as np

from ._bias import predict_bias
from ._bias_residuals import state_derivative


def simulated_biases(spec, ts, sim) -> dict[str, np.ndarray]:
    """Column -> values (times,) of every `[[biases]]` entry of `spec` on the simulation
    `sim` (`dynamics.AsWritten`) at times `ts` (s). Raises `InputError` for an entry
    without `coefficients` (nothing fitted: its column cannot be computed)."""
    if not spec.biases:
        return {}
    rates = np.asarray(state_derivative(sim.model, np.asarray(sim.states)[None],
                                        np.asarray(sim.inputs)[None]))[0]
    return {b.column: predict_bias(b, list(spec.effects), ts, sim.states, rates,
                                   sim.node_names) for b in spec.biases}
