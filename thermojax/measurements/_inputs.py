"""The arrays a model needs from telemetry and chamber profiles, checked.

No maths here and no JAX: this module only reads, checks and arranges data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._errors import InputError
from ..model._spec import ModelSpec
from ._profiles import BUILTIN_PROFILES, Profile, builtin_profile
from ._telemetry import Telemetry, check_inputs, check_sensors, read_telemetry


def model_inputs(spec: ModelSpec, telemetry: Telemetry) -> np.ndarray:
    """The input matrix (times, inputs) in the model's input order, checked finite.

    Raises `InputError` naming the file, column and row of a missing column or
    an empty/non-finite input cell.
    """
    check_inputs(telemetry, spec.input_columns)
    if not spec.input_columns:
        return np.zeros((len(telemetry.ts), 0))
    return np.stack([telemetry.column(c) for c in spec.input_columns], axis=1)


def model_outputs(spec: ModelSpec, telemetry: Telemetry) -> np.ndarray:
    """The measured sensor matrix (times, sensors); NaN marks a dropped sample.

    Raises `InputError` naming the model file when the model has no sensor: there is
    nothing in the data to compare it with.
    """
    if not spec.sensor_columns:
        raise InputError("the model has no sensors, so there is nothing in the data to fit "
                         "or compare it with; add a [[sensors]] table (node = \"...\", "
                         "column = \"...\") naming the node a data column measures.",
                         file=spec.source, field="sensors")
    check_sensors(telemetry, spec.sensor_columns)
    return np.stack([telemetry.column(c) for c in spec.sensor_columns], axis=1)


def profile_inputs(spec: ModelSpec, profile: Profile, baseline_power_w: float = 0.0) -> np.ndarray:
    """Drive a model with a chamber profile: every boundary column sees the chamber
    temperature (°C), every heat-input column the profile's power plus a constant
    `baseline_power_w` (W). Returns (times, inputs) in the model's input order."""
    boundary, heat = set(spec.boundary_columns), set(spec.heat_columns)
    cols = []
    for c in spec.input_columns:
        if c in boundary:
            cols.append(np.asarray(profile.temperature, dtype=float))
        elif c in heat:
            cols.append(np.asarray(profile.power, dtype=float) + baseline_power_w)
    if not cols:
        return np.zeros((len(profile.ts), 0))
    return np.stack(cols, axis=1)


def load_profile(name_or_path: str, dt: float = 1.0) -> Profile | Telemetry:
    """A built-in profile by name (`calibration`, `ramp5`, ...), or a telemetry CSV file."""
    if name_or_path in BUILTIN_PROFILES:
        return builtin_profile(name_or_path, dt=dt)
    path = Path(name_or_path)
    if path.suffix.lower() == ".csv" and not path.exists():
        raise InputError("no such file; check the path given to --profile, or name a built-in "
                         f"profile ({', '.join(sorted(BUILTIN_PROFILES))}).", file=str(path),
                         field="--profile")
    if path.suffix.lower() == ".csv" or path.exists():
        return read_telemetry(path)
    raise InputError(f"'{name_or_path}' is neither a built-in profile ({sorted(BUILTIN_PROFILES)}) "
                     "nor an existing CSV file.", field="--profile")
