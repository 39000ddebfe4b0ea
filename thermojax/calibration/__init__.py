"""Calibration: data conditioning, static polynomial from dwell plateaus, Allan deviation,
the calibration pipeline's named stages (`run_pipeline`, `thermojax calibrate`), and a
unit's end-of-line trim (`estimate_trim`, `thermojax trim`).

The building blocks are NumPy/SciPy only (no JAX); the pipeline's `thermal_fit`,
`coupling` and `verify` stages use `thermojax.fit` and the observer export.
"""

from ._allan import (AllanDeviation, Estimate, NoiseParameters, allan_deviation,
                     noise_parameters)
from ._conditioning import (ORIENTATIONS, OrientationSeparation, Outliers, Synchronized,
                            label_orientations, remove_outliers, separate_orientation_bias,
                            synchronize)
from ._hysteresis import hysteresis_loop_area
from ._plateaus import Plateau, StaticPolynomial, find_plateaus, fit_static_polynomial
from ._config import STAGES, CalibrationConfig, RunFiles, load_config
from ._pipeline import (CalibrationResults, ChannelAllan, ChannelCheck, ChannelPolynomial,
                        ConditionedRun, Coupling, condition, coupling, run_pipeline,
                        static_polynomial, thermal_fit, verification_allan, verify)
from ._plots import plot_allan, plot_trim
from ._report import write_results
from ._synthetic import synthetic_imu_logs
from ._trim import TrimEstimate, estimate_trim, trim_outputs

__all__ = [
    "AllanDeviation", "Estimate", "NoiseParameters", "ORIENTATIONS", "OrientationSeparation",
    "Outliers", "Plateau", "StaticPolynomial", "Synchronized", "allan_deviation",
    "find_plateaus", "fit_static_polynomial", "hysteresis_loop_area", "label_orientations",
    "noise_parameters",
    "plot_allan", "remove_outliers", "separate_orientation_bias", "synchronize",
    "STAGES", "CalibrationConfig", "RunFiles", "load_config", "CalibrationResults",
    "ChannelCheck", "ChannelPolynomial", "ConditionedRun", "Coupling", "condition",
    "coupling", "run_pipeline", "static_polynomial", "thermal_fit", "verify",
    "ChannelAllan", "verification_allan",
    "write_results", "synthetic_imu_logs", "plot_trim", "TrimEstimate", "estimate_trim",
    "trim_outputs",
]
