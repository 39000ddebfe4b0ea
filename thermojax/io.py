"""Files in and out: model TOML, telemetry CSV, and the arrays a model needs from them.

A convenience namespace (`thermojax.io.model_inputs(spec, telemetry)`); the code lives
in `thermojax.model` (model files) and `thermojax.measurements` (telemetry, profiles).
"""

from ._errors import InputError
from .measurements._inputs import load_profile, model_inputs, model_outputs, profile_inputs
from .measurements._telemetry import Telemetry, read_telemetry, write_telemetry
from .model._model_file import dump_model, load_model, parse_model, save_model

__all__ = [
    "InputError", "load_model", "parse_model", "save_model", "dump_model", "read_telemetry",
    "write_telemetry", "Telemetry", "model_inputs", "model_outputs", "profile_inputs",
    "load_profile",
]
