"""How finely a fit integrates a model with nonlinear effects.

ETD2 (`dynamics._nonlinear`) integrates the linear part exactly; its error comes from
the nonlinear rate changing within a step and falls as the square of the step. A mild
nonlinearity (radiation between a slow housing and the chamber) is integrated to within
2e-5 °C by one step per sample period; a temperature-dependent conductance at a fast
die needs four to eight. Every substep is paid in every residual evaluation and every Jacobian
of the fit, so a fit takes the fewest substeps of `SUBSTEP_LADDER` whose estimated error
(`etd2_error`) is below `ERROR_SHARE` of the smallest sensor noise std: at its start
values (`start_tolerance`, `_problem.prepare`) and again at its solution
(`_output_error`), since the parameters may have moved to where the nonlinearity is
stronger; there, too few substeps mean another solve from the solution with more.

A Kalman fit asks what its likelihood needs instead (`fewest_kalman_substeps`): the
filter corrects the state every sample, so only one sample's error, not the free run's,
reaches it; but it reaches it at every sample, against a one-step prediction error near
the sensor noise, so the extended filter steps with a fourth-order scheme
(`dynamics._etdrk4`), whose error falls as the fourth power of the substep. On a
7,000-sample building log with a temperature-dependent heating medium, −log L was within
0.05 of its converged value at 2 of its substeps where ETD2 needed 16; at PRBS1's
four-effect model (a fast heater mass) 2 against ETD2's more than 8 (`_etdrk4`).
It is checked at the start values (a start far from the data is solved in at most
`_kalman_fit.START_SUBSTEPS`) and again at the solution (`_kalman_fit`), and only the
solution's need is remembered.
Fits of one structure share the most any of them needed (`shared_substeps`), Kalman and
output-error fits each their own.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools

import jax
import numpy as np

from ..dynamics._nonlinear import etd2_error
from ._likelihood import kalman_nll_in_substeps
from ..measurements._data import Dataset
from ..model._model import DEFAULT_ETD2_SUBSTEPS, DEFAULT_NOISE

SUBSTEP_LADDER = (1, 2, 4, 8, 16)  # substeps per sample period a fit chooses from
ERROR_SHARE = 0.01  # integration error allowed, as a share of the smallest noise std
ERROR_FLOOR = 1e-6  # °C: the tolerance never goes below this (no sensor resolves it)
START_MARGIN = 2.0  # at the start values the error must be this many times smaller
# −log L a Kalman fit's integration may be off by: a fortieth of the smallest
# likelihood-ratio step the loop tests (χ²₁ at 95 %, 1.92 in −log L)
KALMAN_TOLERANCE = 0.05


def integration_tolerance(sensor_sigma) -> float:
    """The integration error (°C) allowed for sensors of noise stds `sensor_sigma` (°C)."""
    return max(ERROR_SHARE * float(np.min(sensor_sigma)), ERROR_FLOOR)


def start_tolerance(sensor_sigma) -> float:
    """The integration error (°C) allowed at a fit's start values: `integration_tolerance`
    of the starting noise stds (°C), but at most that of a `DEFAULT_NOISE` sensor (a
    refit starts from the stds of a fit without its effect, inflated by the misfit the
    effect removes), over `START_MARGIN`."""
    return min(integration_tolerance(sensor_sigma),
               integration_tolerance([DEFAULT_NOISE])) / START_MARGIN


def fewest_substeps(state, data: Dataset, tolerance: float, read_states: bool = False,
                    at_least: int = 1) -> tuple[int, float]:
    """`(substeps, estimated error °C)`: the fewest of `SUBSTEP_LADDER`, and at least
    `at_least`, that simulate `state` (a `FitState` with a nonlinear model) within
    `tolerance` °C (the last one unchecked, error NaN). `read_states`: the node
    temperatures count too (bias columns are indexed to them)."""
    # one compiled check for every number of substeps (traced), whatever the model's
    model = dataclasses.replace(state.model, read_states=read_states,
                                etd2_substeps=DEFAULT_ETD2_SUBSTEPS)
    for substeps in [s for s in SUBSTEP_LADDER[:-1] if s >= at_least]:
        error = float(etd2_error(model, data, state.run_initial,
                                 jax.device_put(np.asarray(substeps))))
        if error <= tolerance:
            return substeps, error
    return SUBSTEP_LADDER[-1], float("nan")


def fewest_kalman_substeps(state, data: Dataset, tolerance: float | None = None,
                           at_most: int = SUBSTEP_LADDER[-1]) -> tuple[int, float]:
    """`(substeps, estimated error in −log L)`: the fewest of `SUBSTEP_LADDER` whose
    Kalman −log L of `state` (a `FitState` with a nonlinear model)
    differs from the same filter's in four times as many substeps by at most
    `tolerance` (`KALMAN_TOLERANCE` when None) × 255/256 (the filter's error falls as
    the fourth power of the step); the last one unchecked, error NaN. A filter that
    fails (non-finite −log L) takes the last. `at_most`: the ladder ends there where the
    filter is finite, whatever the error (a fit's start: its solution decides how many
    it needs)."""
    tolerance = KALMAN_TOLERANCE if tolerance is None else tolerance
    model = dataclasses.replace(state.model, etd2_substeps=DEFAULT_ETD2_SUBSTEPS)

    @functools.cache
    def nll(substeps):  # one compiled program for every number
        return float(kalman_nll_in_substeps(model, data, state.run_initial,
                                            jax.device_put(np.asarray(substeps))))

    for substeps in SUBSTEP_LADDER[:-1]:
        error = (256 / 255) * abs(nll(substeps) - nll(4 * substeps))
        # (error <= tolerance is False for NaN)
        if error <= tolerance or (substeps >= at_most and np.isfinite(nll(substeps))):
            return substeps, error
    return SUBSTEP_LADDER[-1], float("nan")


# The most substeps a fit of each model structure (its static part) has needed in this
# process: later fits of the structure take at least as many, so that they share one
# compiled program instead of compiling one per number (a refit's two starts, its
# held-out folds). Fits run side by side (`_side_by_side`) each read and write a copy,
# taken before any of them ran (`substep_memory`).
_NEEDED = contextvars.ContextVar("thermojax_substeps", default={})  # the process's


def _remember(needed: dict, key, substeps: int) -> int:
    needed[key] = max(needed.get(key, 0), substeps)
    return needed[key]


def shared_substeps(model, substeps: int, kalman: bool = False, remember: bool = True
                    ) -> int:
    """`substeps` for a fit of `model`, or more if a fit of the same structure (and
    likelihood: `kalman`) needed more earlier in this process; remembered for the fits
    after it (unless not `remember`: a Kalman fit's start, which its solution checks
    again; a start far from the data, such as the user's values, can need 16 substeps
    where every solution needs 4)."""
    key = (kalman, jax.tree.structure(dataclasses.replace(model, etd2_substeps=0)))
    needed = _NEEDED.get()
    return _remember(needed, key, substeps) if remember else max(needed.get(key, 0),
                                                                 substeps)


def substep_snapshot() -> dict:
    """A copy of what the fits so far needed, for a fit run side by side with others."""
    return dict(_NEEDED.get())


@contextlib.contextmanager
def substep_memory(memory: dict):
    """Fits inside read and write `memory` (a `substep_snapshot`) instead."""
    token = _NEEDED.set(memory)
    try:
        yield
    finally:
        _NEEDED.reset(token)


def merge_substeps(memory: dict) -> None:
    """Keep what the fits of `memory` needed, as if they had run here."""
    for key, substeps in memory.items():
        _remember(_NEEDED.get(), key, substeps)


def with_substeps(state, substeps: int):
    """`state` (a `FitState`) with its model integrated in `substeps` per sample period."""
    return dataclasses.replace(state, model=dataclasses.replace(state.model,
                                                                etd2_substeps=substeps))
