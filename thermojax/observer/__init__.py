"""Observer design: observability and sensor placement, gains (pole placement and the
steady-state Kalman filter), the observer in JAX, and lag compensation by input
reconstruction."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._adaptive import AdaptiveRun, adaptive_design, track_conductances
from ._design import design_observer
from ._export import ExportResult, export_observer
from ._input_reconstruction import augment_unknown_input, reconstruction_observer
from ._kalman import KalmanGain, discrete_process_covariance, steady_state_kalman
from ._observability import (Observability, observability, observability_gramian,
                             observability_matrix, observability_rank)
from ._observer import Observer, ObserverRun, run_observer
from ._placement import SensorSet, sensor_placement
from ._pole_placement import ObserverPoles, observer_poles, place_observer_gain
from ._response import estimate_noise_std, rise_time
from ._schedule import scheduled_design
from ._trim import TrimFactor, TrimPlan, load_trim_plan, parse_trim_plan, trim_design

__all__ = [
    "AdaptiveRun", "ExportResult", "adaptive_design", "KalmanGain", "Observability", "Observer", "ObserverPoles", "ObserverRun",
    "SensorSet", "augment_unknown_input", "design_observer", "discrete_process_covariance",
    "estimate_noise_std", "export_observer", "observability", "observability_gramian",
    "observability_matrix", "observability_rank", "observer_poles", "place_observer_gain",
    "reconstruction_observer", "rise_time", "run_observer", "sensor_placement",
    "scheduled_design", "steady_state_kalman", "track_conductances", "TrimFactor", "TrimPlan",
    "load_trim_plan", "parse_trim_plan", "trim_design",
]
