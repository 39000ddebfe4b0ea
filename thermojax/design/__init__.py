"""Experiment design: the chamber profile, within the chamber's limits, that best
determines a model's parameters, judged against reference profiles of the same length."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._criterion import CRITERIA, PRIOR_LOG_STD, criterion_loss
from ._design import Design, Evaluated, design
from ._information import (InformationProblem, information_problem, marginal_information,
                           predicted_stds)
from ._limits import ChamberLimits
from ._references import REFERENCES, reference_profile
from ._report import design_report, std_ratios, write_design
from ._schedule import ProfileSchedule

__all__ = [
    "CRITERIA", "ChamberLimits", "Design", "Evaluated", "InformationProblem", "PRIOR_LOG_STD",
    "ProfileSchedule", "REFERENCES", "criterion_loss", "design", "design_report",
    "information_problem", "marginal_information", "predicted_stds", "reference_profile",
    "std_ratios", "write_design",
]
