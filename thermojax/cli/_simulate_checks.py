"""`simulate`'s arguments checked against the model and the profile before any work:
a plausible `--power` that the model can take, a `--seed` NumPy accepts, and a sample
count (`--dt`) whose arrays fit in memory."""

from __future__ import annotations

import numpy as np

from .._errors import InputError
from .._sizes import check_memory

#: W: beyond this no lumped thermal model of a device is driven (a megawatt).
MAX_POWER_W = 1e6
#: Bytes per sample and per column of a simulation (inputs, states, readings, padding and
#: the CSV text), a generous estimate.
BYTES_PER_CELL = 64.0


def check_seed(seed: int) -> None:
    if not 0 <= seed < 2 ** 63:
        raise InputError(f"the noise seed must be a whole number from 0 to 2**63 - 1, got "
                         f"{seed}.", field="--seed")


def check_power(power: float, spec, source_is_file: bool, model_file: str) -> None:
    """`--power` W: finite, within `MAX_POWER_W`, given only where it reaches a heat input."""
    if power == 0.0:
        return
    if not np.isfinite(power) or abs(power) > MAX_POWER_W:
        raise InputError(f"{power:g} W is not a plausible power (at most {MAX_POWER_W:g} W in "
                         "magnitude); give the heater's power in watts.", field="--power")
    if source_is_file:
        raise InputError("--power adds to the heat inputs of a built-in profile; the profile "
                         "is a CSV file, whose own columns drive the model. Put the power in "
                         "its heat-input column instead.", field="--power")
    if not spec.heat_columns:
        raise InputError("the model has no heat inputs ([[heat_inputs]]), so --power would "
                         "drive nothing; drop --power or add a heat input to the model.",
                         file=model_file, field="--power")


def check_profile_size(profile_name: str, dt: float, n_columns: int) -> int:
    """The predicted number of samples of a built-in profile at `dt` s, refused (naming
    `--dt` and the memory it would need) when its arrays cannot fit; before any profile
    is built at that period."""
    from ..measurements._profiles import builtin_profile

    coarse = builtin_profile(profile_name, dt=1.0)
    duration = float(coarse.ts[-1] - coarse.ts[0])
    n = duration / dt + 1.0
    check_memory(n * max(n_columns, 1) * BYTES_PER_CELL,
                 f"the profile '{profile_name}' ({duration:g} s) at --dt {dt:g} s "
                 f"({n:.3g} samples)", fix="Give a longer --dt.", field="--dt")
    return int(n)


def check_profile_columns(spec, profile_name: str, model_file: str) -> None:
    """A built-in profile drives boundary and heat-input columns only: another column the
    model reads (an effect's input, a name in an expression) is refused, named."""
    driven = set(spec.boundary_columns) | set(spec.heat_columns)
    for c in spec.input_columns:
        if c not in driven:
            raise InputError(f"the model's effects read the input column '{c}' (an effect's "
                             "input, or a name in an expression that is neither a node nor a "
                             "parameter), which the built-in profile "
                             f"'{profile_name}' does not drive; check the spelling, or "
                             "simulate from a CSV profile holding that column.",
                             file=model_file, field=c)
