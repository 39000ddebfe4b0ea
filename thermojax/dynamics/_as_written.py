"""A model file simulated as written: its effects lowered and applied, with the simulator
the fit uses (the blocked exact-hold recurrence, or ETD2 where the model is nonlinear).

`simulate` and `demo` write telemetry from it, so a file they write is what `fit`
would predict for the same model: an offset, a lag, an extra node or radiation in
`[[effects]]` is in the output, never silently left out.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import InputError

@dataclasses.dataclass(frozen=True)
class AsWritten:
    """A simulation of a model as written: `states` (times, nodes) °C of every node of the
    lowered network (`node_names`, the file's nodes then the nodes effects add),
    `outputs` (times, sensors) °C in `sensor_columns` order, readings with every sensor
    effect applied; `nonlinear`: whether ETD2 was used; `model` the `ThermalModel`
    simulated and `inputs` (times, inputs) in its (the lowered network's) column order."""

    states: np.ndarray
    outputs: np.ndarray
    node_names: tuple[str, ...]
    sensor_columns: tuple[str, ...]
    nonlinear: bool
    model: object = dataclasses.field(repr=False, default=None)
    inputs: np.ndarray | None = dataclasses.field(repr=False, default=None)


def simulate_as_written(spec, ts: np.ndarray, inputs: np.ndarray) -> AsWritten:
    """Simulate `spec` (a `ModelSpec`, effects included) on a uniform grid `ts` (s) with
    `inputs` (times, inputs) in `spec.input_columns` order, from the model's initial state
    (its `initial` values, the other nodes at equilibrium with the first input)."""
    from ..measurements._data import Dataset, Experiment
    from ..model._model import ThermalModel
    from ..model.effects import lower_effects
    from ._sensitivity import dataset_block_outputs

    lowered = lower_effects(spec).spec
    missing = [c for c in lowered.input_columns if c not in spec.input_columns]
    if missing:
        raise InputError(f"the model's effects need the input column(s) {', '.join(missing)}, "
                         "which the profile does not give.", file=str(spec.source),
                         field="effects")
    order = [spec.input_columns.index(c) for c in lowered.input_columns]
    u = np.asarray(inputs, float)[:, order]
    model = dataclasses.replace(ThermalModel.from_spec(lowered), read_states=True)
    p = len(lowered.sensor_columns)
    data = Dataset.from_experiments([Experiment(np.asarray(ts, float), u,
                                                np.zeros((len(ts), p)))])
    y = np.asarray(dataset_block_outputs(model, data))[0]
    y = y.reshape(-1, y.shape[-1])[:len(ts)]  # whole blocks -> samples
    return AsWritten(states=y[:, p:], outputs=y[:, :p], node_names=tuple(lowered.node_names),
                     sensor_columns=tuple(lowered.sensor_columns),
                     nonlinear=bool(model.is_nonlinear), model=model, inputs=u)
