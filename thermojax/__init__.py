"""thermojax: differentiable grey-box identification of lumped-parameter thermal networks.

The everyday API is re-exported lazily (module-level `__getattr__`) from the stage
subpackages, in the order data flows through them: `model` -> `measurements` ->
`dynamics` -> `fitting` -> `discovery` -> `investigation`, with `cli` on top. `import thermojax`
alone loads no JAX. Importing any stage switches JAX to float64 (`jax_enable_x64`):
stiff thermal networks need it; and, unless `XLA_FLAGS` says otherwise, turns XLA's CPU
fusion emitters off, which halves compilation (`_jax_settings`).
"""

import importlib

__version__ = "0.1.0"

# Each public name and the stage that defines it.
_STAGES = {
    "model": ["ModelSpec", "Parameter", "Effect", "load_model", "parse_model", "save_model",
              "dump_model", "Topology", "ThermalNetwork", "StableDynamics", "LinearSystem",
              "DiscreteSystem", "ThermalModel", "parameter_mask", "free_parameters",
              "with_free_parameters"],
    "measurements": ["Telemetry", "read_telemetry", "write_telemetry", "Profile",
                     "builtin_profile", "Experiment", "Dataset"],
    "dynamics": ["discretize", "discretize_process_noise", "AbstractDiscretization",
                 "MatrixExponential", "Modal", "Tustin", "ForwardEuler", "simulate",
                 "simulate_batch", "steady_state", "Solution", "AbstractSimulator", "ExactHold",
                 "DiffraxSimulator"],
    "fitting": ["fit", "FitResult", "profile_interval", "TruncatedGaussNewton", "kalman_nll",
                "simulate_dataset", "identifiability", "comparison_table", "write_fit_outputs",
                "fit_bias"],
    "discovery": ["missing_heat", "write_missing_heat", "MissingHeat", "LIBRARY",
                  "LibraryTerm"],
    "investigation": ["investigate", "diagnose", "evaluate"],
    "observer": ["Observer", "run_observer", "design_observer", "observability",
                 "sensor_placement", "observer_poles", "place_observer_gain",
                 "steady_state_kalman", "reconstruction_observer"],
    "cli": ["perturbed", "demo_runs"],
}
_LAZY = {name: "." + stage for stage, names in _STAGES.items() for name in names}
_LAZY["InputError"] = "._errors"
_LAZY["enable_compilation_cache"] = ".compilation._cache"
_SUBMODULES = {"io", *_STAGES}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name in _SUBMODULES:
        return importlib.import_module("." + name, __name__)
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'thermojax' has no attribute '{name}'")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
