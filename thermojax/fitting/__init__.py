"""Fitting: likelihoods (output error, Kalman), solvers, `fit()`, uncertainty,
identifiability, bias channels and the fit report."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._bias import BiasFit, fit_bias
from ._correlated_noise import CorrelatedNoiseStds, correlated_noise_stds
from ._fit import FitResult, fit, profile_interval
from ._fit_report import comparison_table, write_fit_outputs
from ._identifiability import Identifiability, identifiability
from ._likelihood import kalman_nll, simulate_dataset
from ._solver import TruncatedGaussNewton

__all__ = [
    "BiasFit", "CorrelatedNoiseStds", "FitResult", "Identifiability", "TruncatedGaussNewton", "comparison_table",
    "correlated_noise_stds", "fit", "fit_bias", "identifiability", "kalman_nll", "profile_interval", "simulate_dataset",
    "write_fit_outputs",
]
