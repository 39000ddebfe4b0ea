"""The reference observer a firmware engineer can run and trust bit for bit.

NumPy and the standard library only (no JAX): the filter-form observer with
first-order-hold inputs in float64/float32 and in fixed point (Q16.16, Q8.24, Q15, Q31), the
bias channels evaluated from the estimate (polynomial,
gradients, exact rates, viscoelastic strain states), the firmware's channel supervision (plausibility, open circuit, ADC rails, wire break,
reduced-order fallback gains; untrusted inputs held at their last good value, state
health and fixed-point saturation counts), multi-rate bias interpolation through a double buffer, an adaptive filter tracking drifting
conductances, a gain-scheduled observer, an observer trimmed per unit at initialisation,
the derived fixed-point error bound, and a C99 generator that repeats all of it.
"""

from ._adaptive import AdaptiveDesign, AdaptiveReference, AdaptiveReferenceRun
from ._adaptive_c import generate_adaptive_c, pack_adaptive, unpack_adaptive
from ._artifact import ArtifactError, ObserverArtifact, load_observer
from ._bias import BiasChannel, BiasEvaluator, FixedBiasEvaluator, bias_channels_from_metadata
from ._bound import ErrorBound, error_series, quantization_error_bound
from ._c_source import CSource, generate_c
from ._faults import ChannelMonitor, FaultConfig, default_input_limits
from ._fixed import FixedObserver, FixedScaling
from ._float import FloatObserver
from ._formats import (FORMATS, Q15, Q31, Q8_24, Q16_16, FixedFormat, decode, encode, fixed_format,
                       round_shift, saturate)
from ._multirate import BiasInterpolator, DoubleBuffer, MultiRateRun, run_multirate
from ._multirate_c import generate_multirate_c, pack_multirate
from ._run import ObserverRun
from ._scheduled import ScheduledDesign, ScheduledObserver, ScheduledRun
from ._scheduled_c import generate_scheduled_c, pack_scheduled, unpack_scheduled
from ._system import ObserverSystem
from ._trimmed import Trim, TrimDesign, TrimmedObserver, trim_matrices
from ._trimmed_c import generate_trimmed_c, pack_trimmed, unit_factor_table, unpack_trimmed

__all__ = [
    "AdaptiveDesign", "AdaptiveReference", "AdaptiveReferenceRun", "generate_adaptive_c",
    "pack_adaptive", "unpack_adaptive", "ArtifactError", "BiasChannel", "BiasEvaluator", "FixedBiasEvaluator", "BiasInterpolator", "CSource", "ChannelMonitor", "DoubleBuffer",
    "ErrorBound", "FORMATS", "FaultConfig", "FixedFormat", "FixedObserver", "FixedScaling",
    "FloatObserver", "MultiRateRun", "ObserverArtifact", "ObserverRun", "ObserverSystem",
    "Q15", "Q16_16", "Q31", "Q8_24", "decode", "encode", "error_series", "fixed_format",
    "bias_channels_from_metadata", "default_input_limits", "generate_c", "generate_multirate_c", "pack_multirate", "load_observer", "quantization_error_bound", "round_shift",
    "run_multirate", "saturate", "ScheduledDesign", "ScheduledObserver", "ScheduledRun",
    "generate_scheduled_c", "pack_scheduled", "unpack_scheduled", "Trim", "TrimDesign",
    "TrimmedObserver", "trim_matrices", "generate_trimmed_c", "pack_trimmed",
    "unit_factor_table", "unpack_trimmed",
]
