"""Measured runs as arrays: one `Experiment` per chamber run, a padded `Dataset` for vmap."""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Bool, Float

from .._errors import InputError
from ..model._spec import ModelSpec
from ._telemetry import Telemetry


@dataclass(frozen=True)
class Experiment:
    """One chamber run: uniformly sampled inputs and (possibly gappy) measurements.

    `inputs` (times, inputs) in the model's input order; `outputs` (times,
    sensors) with NaN for dropped samples; `ts` (s); `name` for reports; `biases`
    (times, bias columns) in the model's `[[biases]]` order, NaN where missing, or
    None when the model has no bias channel.
    """

    ts: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    name: str = "run"
    biases: np.ndarray | None = None

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.ts)))

    @property
    def n_times(self) -> int:
        return len(self.ts)

    @classmethod
    def from_telemetry(cls, spec: ModelSpec, telemetry: Telemetry, name: str | None = None,
                       extra_outputs: tuple[str, ...] = ()) -> "Experiment":
        """Pick the model's columns out of a telemetry file, checking them.

        Raises `InputError` for a missing column, an input gap, an all-NaN
        sensor, or fewer than two samples.
        """
        from ._inputs import model_inputs, model_outputs

        file = telemetry.path or name or "data"
        u = model_inputs(spec, telemetry)
        y = model_outputs(spec, telemetry)
        if extra_outputs:
            y = np.concatenate([y, np.stack([telemetry.column(c) for c in extra_outputs], 1)], 1)
        if len(telemetry.ts) < 2:
            raise InputError("a run needs at least two samples.", file=file, field="time_s")
        if not np.isfinite(y).any():
            raise InputError("no sensor data in this run: every sensor cell is empty or NaN.",
                             file=file, field=",".join(spec.sensor_columns))
        biases = None
        if spec.biases:
            biases = np.stack([np.asarray(telemetry.column(b.column), float)
                               for b in spec.biases], 1)
            for j, b in enumerate(spec.biases):
                if not np.isfinite(biases[:, j]).any():
                    raise InputError(f"bias column '{b.column}' has no readings in this run "
                                     "(every cell is empty or nan); record it, or drop its "
                                     "[[biases]] entry from the model.", file=file,
                                     field=b.column)
        return cls(np.asarray(telemetry.ts, float), u, y, name or file, biases)


class Dataset(eqx.Module):
    """Several runs padded to one length, for vmapped simulation and likelihoods.

    Padding repeats each run's last input and marks its outputs unmeasured, so
    it never changes a likelihood. `mask[r, k, j]` is True where sensor `j` of
    run `r` was measured at sample `k`; `outputs` holds 0 where it was not.
    """

    ts: Float[Array, "runs times"]
    dt: Float[Array, " runs"]
    inputs: Float[Array, "runs times inputs"]
    outputs: Float[Array, "runs times outputs"]
    mask: Bool[Array, "runs times outputs"]
    lengths: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)

    @classmethod
    def from_experiments(cls, experiments: list[Experiment]) -> "Dataset":
        if not experiments:
            raise InputError("no runs given; pass at least one --data file.", field="--data")
        longest = max(e.n_times for e in experiments)
        ts, u, y, mask, dts = [], [], [], [], []
        for e in experiments:
            pad = longest - e.n_times
            dt = e.dt
            ts.append(np.concatenate([e.ts, e.ts[-1] + dt * np.arange(1, pad + 1)]))
            u.append(np.concatenate([e.inputs, np.repeat(e.inputs[-1:], pad, 0)]))
            measured = np.isfinite(e.outputs)
            y.append(np.concatenate([np.where(measured, e.outputs, 0.0),
                                     np.zeros((pad, e.outputs.shape[1]))]))
            mask.append(np.concatenate([measured, np.zeros((pad, e.outputs.shape[1]), bool)]))
            dts.append(dt)
        # `device_put`, not `jnp.asarray`: the latter compiles a small program per shape.
        return cls(*jax.device_put((np.stack(ts), np.array(dts), np.stack(u), np.stack(y),
                                    np.stack(mask))), tuple(e.n_times for e in experiments),
                   tuple(e.name for e in experiments))

    @property
    def n_runs(self) -> int:
        return len(self.lengths)
