"""Telemetry files, chamber profiles, and the experiments and datasets a fit reads."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._data import Dataset, Experiment
from ._inputs import load_profile, model_inputs, model_outputs, profile_inputs
from ._plausibility import Outlier, check_plausibility
from ._profiles import Profile, builtin_profile
from ._telemetry import Telemetry, read_telemetry, write_telemetry

__all__ = [
    "Dataset", "Experiment", "Outlier", "Profile", "Telemetry", "builtin_profile",
    "check_plausibility", "load_profile",
    "model_inputs", "model_outputs", "profile_inputs", "read_telemetry", "write_telemetry",
]
