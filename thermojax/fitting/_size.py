"""How much a fit of a large network costs, said before the work and refused when it
cannot fit in memory.

A fit's exact sensitivities carry one `2n × 2n` block of the augmented exponential per
free parameter, so its memory grows like `P (2n)²` and its time like `P n³` (`n` states,
`P` free parameters). Measured on the 2-core, 24 GiB development machine with chains of
`n` nodes and `P = 2n + 1` free parameters, 565 samples (benchmarks/README.md, "Large
networks"): n = 40 peaked at 0.72 GB in 32 s, n = 80 at 1.19 GB in 381 s, and a
200-node chain reached 8.9 GB without a result after 7 minutes. The constants below
fit those figures (about 0.6 GB of runtime and compiled programs, plus
`BYTES_PER_ENTRY · P (2n)²`); the time is the machine's, a rough guide elsewhere.
"""

from __future__ import annotations

import dataclasses

from .._errors import InputError
from .._sizes import available_memory

BASE_BYTES = 0.6e9
BYTES_PER_ENTRY = 146.0           # bytes per entry of the P blocks of (2n)²
SECONDS_PER_WORK = 381.0 / (161 * 80 ** 3)   # per unit of P n³ (the n = 80 chain)
#: Above this share of the memory available now, a fit is refused before it starts.
MEMORY_SHARE = 0.8


@dataclasses.dataclass(frozen=True)
class FitCost:
    """The predicted peak memory (`bytes`) and time (`seconds`) of one fit of `n_states`
    states with `n_free` free parameters."""

    n_states: int
    n_free: int
    bytes: float
    seconds: float


def fit_cost(n_states: int, n_free: int) -> FitCost:
    """`FitCost` of a fit (see the module docstring for the model and its data)."""
    n, P = int(n_states), int(n_free)
    return FitCost(n, P, BASE_BYTES + BYTES_PER_ENTRY * P * (2 * n) ** 2,
                   SECONDS_PER_WORK * P * n ** 3)


def check_fit_size(n_states: int, n_free: int, source=None, available=None) -> FitCost:
    """Refuse (`InputError`) a fit whose predicted memory exceeds `MEMORY_SHARE` of what
    is available (`available` bytes, default now); return its `FitCost`."""
    cost = fit_cost(n_states, n_free)
    available = available_memory() if available is None else available
    if available is not None and cost.bytes > MEMORY_SHARE * available:
        raise InputError(
            f"fitting {n_free} free parameters of a {n_states}-state network needs about "
            f"{cost.bytes / 1e9:.1f} GB (the exact sensitivities grow like P·(2n)²) and "
            f"{available / 1e9:.1f} GB are available. Fix the parameters known from design "
            "(`{ value = ..., fixed = true }`), fit a coarser network (merge nodes of one "
            "body), or run on a machine with more memory.", file=source)
    return cost
