"""thermojax: differentiable grey-box identification of lumped-parameter thermal networks.

The JAX API loads lazily (module-level `__getattr__`), so `import thermojax.reference`
and the file readers never import JAX. Importing any JAX name switches JAX to
float64 (`jax_enable_x64`): stiff thermal networks need it.
"""

import importlib

__version__ = "0.1.0"

_LAZY = {
    # model files and telemetry (no JAX)
    "InputError": "._errors",
    "ModelSpec": "._spec",
    "Parameter": "._spec",
    "load_model": "._model_file",
    "parse_model": "._model_file",
    "save_model": "._model_file",
    "dump_model": "._model_file",
    "Telemetry": "._telemetry",
    "read_telemetry": "._telemetry",
    "write_telemetry": "._telemetry",
    "Profile": "._profiles",
    "builtin_profile": "._profiles",
    # JAX core
    "Topology": "._network",
    "ThermalNetwork": "._network",
    "StableDynamics": "._network",
    "LinearSystem": "._system",
    "DiscreteSystem": "._system",
    "discretize": "._discretize",
    "discretize_process_noise": "._discretize",
    "AbstractDiscretization": "._discretize",
    "MatrixExponential": "._discretize",
    "Modal": "._discretize",
    "Tustin": "._discretize",
    "ForwardEuler": "._discretize",
    "simulate": "._simulate",
    "simulate_batch": "._simulate",
    "steady_state": "._simulate",
    "Solution": "._simulate",
    "AbstractSimulator": "._simulate",
    "ExactHold": "._simulate",
    "DiffraxSimulator": "._simulate",
    "fit": "._fit",
    "FitResult": "._fit",
    "profile_interval": "._fit",
    "Experiment": "._data",
    "Dataset": "._data",
    "ThermalModel": "._model",
    "TruncatedGaussNewton": "._solver",
    "kalman_nll": "._likelihood",
    "simulate_dataset": "._likelihood",
    "identifiability": "._identifiability",
    "comparison_table": "._fit_report",
    "write_fit_outputs": "._fit_report",
    "perturbed": "._runner",
    "Effect": "._spec",
    "investigate": "._investigate",
    "diagnose": "._diagnose",
    "evaluate": "._investigate",
    "fit_bias": "._bias",
    "demo_runs": "._demo",
    "parameter_mask": "._parameters",
    "free_parameters": "._parameters",
    "with_free_parameters": "._parameters",
}

_JAX_MODULES = {"._network", "._system", "._discretize", "._simulate", "._parameters", "._fit",
                "._data", "._model", "._solver", "._likelihood", "._fit_report", "._runner",
                "._investigate", "._diagnose", "._demo"}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name == "io":
        return importlib.import_module(".io", __name__)
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'thermojax' has no attribute '{name}'")
    if module in _JAX_MODULES:
        import jax

        jax.config.update("jax_enable_x64", True)
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
