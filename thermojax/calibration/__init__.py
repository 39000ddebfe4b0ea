"""Calibration: data conditioning, static polynomial from dwell plateaus, Allan deviation.

NumPy/SciPy only (no JAX): each stage is a function on arrays.
"""

from ._allan import (AllanDeviation, Estimate, NoiseParameters, allan_deviation,
                     noise_parameters)
from ._conditioning import (ORIENTATIONS, OrientationSeparation, Outliers, Synchronized,
                            label_orientations, remove_outliers, separate_orientation_bias,
                            synchronize)
from ._plateaus import Plateau, StaticPolynomial, find_plateaus, fit_static_polynomial
from ._plots import plot_allan

__all__ = [
    "AllanDeviation", "Estimate", "NoiseParameters", "ORIENTATIONS", "OrientationSeparation",
    "Outliers", "Plateau", "StaticPolynomial", "Synchronized", "allan_deviation",
    "find_plateaus", "fit_static_polynomial", "label_orientations", "noise_parameters",
    "plot_allan", "remove_outliers", "separate_orientation_bias", "synchronize",
]
