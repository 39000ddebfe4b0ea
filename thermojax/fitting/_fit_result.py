"""`FitResult`: a fitted model with its evidence, as `fit` returns it.

On its own so that the likelihoods' fits (`_kalman_fit`, `_output_error`), which take a
`FitResult`, and the summary that builds one (`_summary`), which uses them, import it
without importing each other: the arrows run `_summary` -> fits -> `_fit_result`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model._model import ThermalModel
from ..model._spec import ModelSpec
from ._bias import BiasFit
from ._dominance import DominantSample
from ._identifiability import Identifiability
from ._problem import FitState, _Problem
from ._smoothed import kalman_smoothed


@dataclass
class FitResult:
    """A fitted model with its evidence. Values are physical (J/K, W/K, °C, °C/√s)."""

    spec: ModelSpec  # the fitted model, as a file would hold it
    lowered_spec: ModelSpec  # the same with structural effects as plain entries (`model`'s)
    model: ThermalModel
    state: FitState
    likelihood: str
    parameters: dict[str, dict]  # dotted name -> {"value", "std", "free"}
    correlation: np.ndarray  # among the free parameters, in `free_names` order
    free_names: list[str]
    nll: float
    aic: float
    bic: float
    n_params: int
    n_samples: int
    rmse: dict[str, float]
    fit_percent: dict[str, float]
    per_run: list[dict]
    identifiability: Identifiability
    n_steps: int
    converged: bool
    message: str
    wall_time_s: float
    predictions: list[np.ndarray] = field(repr=False, default_factory=list)  # (times, outputs)
    # Kalman only: the one-step innovations over their std, (runs, times, outputs), 0 where
    # unmeasured (`standardized_innovations`).
    innovations: np.ndarray | None = field(repr=False, default=None)
    theta: np.ndarray | None = field(repr=False, default=None)
    problem: _Problem | None = field(repr=False, default=None)
    # Output error with the default solver: residual evaluations at trial points (each
    # of the `n_steps` iterations also evaluates residuals and Jacobian once).
    n_evaluations: int | None = None
    # Effect parameters fitted through a lowered entry: effect name -> (scale, power),
    # value = scale * lowered value ** power (e.g. a sensor lag's tau = C / G).
    lowered_as: dict[str, tuple[float, float]] = field(repr=False, default_factory=dict)
    # Bias channels (docs/formats.md §4): column -> `BiasFit` on the fitted model's states.
    biases: dict[str, BiasFit] = field(repr=False, default_factory=dict)
    # Samples that alone carry a quarter or more of their sensor's squared error
    # (`_dominance`); the fit is then not converged.
    dominant: list[DominantSample] = field(default_factory=list)
    _smoothed: list | None = field(repr=False, default=None)  # `smoothed`, once computed
    # How the optimum and its curvature were computed, in words: forward sensitivities
    # (the Jacobian formed) or the adjoint path of large networks (`fitting._adjoint`).
    method: str = ""

    @property
    def smoothed(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Kalman only (else empty): RTS-smoothed node temperatures per run, (times, nodes)
        mean and std (°C), computed when first read."""
        if self._smoothed is None:
            self._smoothed = []
            if self.likelihood == "kalman":
                data = self.problem.data
                mean, std = kalman_smoothed(self.model, data, self.state.run_initial)
                self._smoothed = [(np.asarray(mean[r, :n]), np.asarray(std[r, :n]))
                                  for r, n in enumerate(data.lengths)]
        return self._smoothed
