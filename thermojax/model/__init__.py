"""A model as written (spec, TOML file) and as a network: nodes, links, parameters, effects."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from . import effects
from ._model import ThermalModel, model_to_spec
from ._model_file import dump_model, load_model, parse_model, save_model
from ._network import StableDynamics, ThermalNetwork, Topology
from ._parameters import FreeIndex, free_parameters, parameter_mask, with_free_parameters
from ._parameters_by_name import spec_parameters, with_spec_parameters
from ._spec import Bias, Boundary, Effect, HeatInput, Link, ModelSpec, Node, Parameter, Sensor
from ._system import DiscreteSystem, LinearSystem

__all__ = [
    "Bias", "Boundary", "DiscreteSystem", "Effect", "FreeIndex", "HeatInput", "LinearSystem",
    "Link", "ModelSpec", "Node", "Parameter", "Sensor", "StableDynamics", "ThermalModel",
    "ThermalNetwork", "Topology", "dump_model", "effects", "free_parameters", "load_model",
    "model_to_spec", "parameter_mask", "parse_model", "save_model", "spec_parameters",
    "with_free_parameters", "with_spec_parameters",
]
