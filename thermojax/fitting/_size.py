"""How much a fit of a large network costs, which path it takes, said before the work
and refused when it cannot fit in memory.

A fit's exact sensitivities carry one `2n × 2n` block of the augmented exponential per
free parameter, so its memory grows like `P (2n)²` and its time like `P n³` (`n` states,
`P` free parameters). Measured on the 2-core, 24 GiB development machine with chains of
`n` nodes and `P = 2n + 1` free parameters, 565 samples (benchmarks/README.md,
`large_networks.py`, the figures from before the adjoint path): n = 40 peaked at 0.72 GB in 32 s, n = 80 at 1.19 GB in 381 s, and a
200-node chain reached 8.9 GB without a result after 7 minutes. The constants below
fit those figures (about 0.6 GB of runtime and compiled programs, plus
`BYTES_PER_ENTRY · P (2n)²`); the time is the machine's, a rough guide elsewhere.

A long log adds the Jacobian of its residuals: one number per sample, sensor and free
parameter, held about `JACOBIAN_COPIES` times over while a step is taken (the solver's
linearization and the next one). Measured on the six-node IMU (3 sensors, 22 free
parameters, output error): 0.53 GB at 10⁵ samples, 1.85 GB at 10⁶ and 3.22 GB at
2·10⁶, 1.37 GB per 10⁶ samples, 2.6 times the Jacobian's 0.53 GB. A log too long
for the memory at hand (in a fit that cannot take the normal equations below: a Kalman
likelihood, a nonlinear model, bias columns) is refused before the work with what to do
(a shorter stretch, or fewer samples: the thermal time constants seldom need every
one), not ended by the system's out-of-memory killer.

An output-error fit of a linear network without bias columns, with the default solver,
whose residuals' Jacobian would take more than `NORMAL_EQUATIONS_ABOVE_BYTES` (and more
than the network's sensitivities) sums its normal equations over stretches of the log
instead (`fitting._normal_equations`): its memory is the log's copies, not the Jacobian's.
Otherwise such a fit takes the adjoint path (`fitting._adjoint`) where the forward
sensitivities are predicted to take longer than `ADJOINT_ABOVE_S` or not to fit in memory
(`choose_path`). Its
memory grows like the series terms it keeps (`runs · T · d · n`, `d` terms per sample
period) plus the information matrix (`P²`) and, where it takes at most
`ADJOINT_JACOBIAN_BYTES`, the residuals' Jacobian that the information is formed from; its
time like `P` products of a simulation (`P · T · d · (n + e)`); it is refused only where
that memory does not fit (`adjoint_cost`).
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
#: Copies of the residuals' Jacobian (8-byte numbers) a forward-path step holds.
JACOBIAN_COPIES = 2.6


#: s; forward sensitivities predicted to take longer than this: the adjoint path instead.
ADJOINT_ABOVE_S = 60.0
# The adjoint path's constants (benchmarks/README.md, `large_networks.py`): runtime and
# compiled programs, and bytes per kept series term and per information entry.
ADJOINT_BASE_BYTES = 0.6e9
ADJOINT_BYTES_PER_TERM = 8.0 * 3
ADJOINT_BYTES_PER_ENTRY = 8.0 * 4
#: Bytes of the residuals' Jacobian (readings × P) up to which the adjoint path forms the
#: information from its columns (forward products only, twice as fast as forward and
#: reverse pairs) and holds it.
ADJOINT_JACOBIAN_BYTES = 1e9
#: Free parameters beyond which, where that Jacobian is too large to hold, the adjoint
#: path's information is the local one (`_local_information`: a few hundred compressed
#: products whatever `P`; 1,500 pairs would take about 2 minutes at 500 nodes).
LOCAL_INFORMATION_ABOVE = 1500
#: The local information's cost in the time forecast, as this many parameters' products
#: (a 1,000-node chain, 3,001 parameters: 357 s, 2026-12-07).
LOCAL_INFORMATION_AS_PARAMS = 900
#: Compressed products the local information holds (a chain at radius 40: 3 · 81).
LOCAL_COLOURS = 243
ADJOINT_BASE_S = 10.0  # compilation
# per unit of 3 P · T · d · n (d = 30): 13, 21 and 61 s at n = 50, 100, 200 (2026-12-07)
ADJOINT_SECONDS_PER_WORK = 1.15e-8


#: Bytes of the forward path's residual Jacobian (its copies included) above which a fit
#: that may take it (`choose_path`) sums normal equations over stretches of the log
#: instead (`fitting._normal_equations`), where that Jacobian outweighs the network's
#: sensitivities. Below it the forward path is faster where it fits (the six-node IMU at
#: 10⁶ samples: 14.5 s and 1.54 GB against 26.6 s and 0.66 GB).
NORMAL_EQUATIONS_ABOVE_BYTES = 2e9
#: The normal-equations path's constants, from the six-node IMU (3 sensors, 19 free
#: parameters; benchmarks/README.md, `long_logs.py`): 0.67 GB and 26 s at 10⁶ samples,
#: 2.41 GB and 259 s at 10⁷. Runtime and compiled programs, then per sensor reading the
#: log's copies (the run as read, its padded device copy, the predictions and the
#: reports' residuals: about eight numbers), and the time per unit of readings × P²
#: (each step one pass with the Jacobian and one or two without, ~16 steps from 30 % off).
NORMAL_EQUATIONS_BASE_BYTES = 0.5e9
NORMAL_EQUATIONS_BYTES_PER_READING = 64.0
NORMAL_EQUATIONS_BASE_S = 10.0
NORMAL_EQUATIONS_SECONDS_PER_WORK = 2.3e-8


@dataclasses.dataclass(frozen=True)
class FitCost:
    """The predicted peak memory (`bytes`) and time (`seconds`) of one fit of `n_states`
    states with `n_free` free parameters."""

    n_states: int
    n_free: int
    bytes: float
    seconds: float
    jacobian_bytes: float = 0.0  # of `bytes`: the residuals' Jacobian (a long log's)


def fit_cost(n_states: int, n_free: int, n_readings: int = 0) -> FitCost:
    """`FitCost` of a fit by forward sensitivities (see the module docstring for the model
    and its data); `n_readings`: the sensor readings fitted (samples × sensors, over every
    run), whose Jacobian adds `JACOBIAN_COPIES · 8 · n_readings · P` bytes."""
    n, P = int(n_states), int(n_free)
    jacobian = JACOBIAN_COPIES * 8.0 * int(n_readings) * P
    return FitCost(n, P, BASE_BYTES + BYTES_PER_ENTRY * P * (2 * n) ** 2 + jacobian,
                   SECONDS_PER_WORK * P * n ** 3, jacobian)


def adjoint_cost(n_states: int, n_free: int, n_samples: int, terms: int = 30,
                 n_readings: int = 0) -> FitCost:
    """`FitCost` of the adjoint path: `n_samples` samples over all runs, `terms` series
    terms per sample period (`dynamics._taylor_hold.taylor_plan`), `n_readings` sensor
    readings (samples × sensors over every run: the Jacobian the information is formed
    from, where it is held)."""
    n, P, T = int(n_states), int(n_free), int(n_samples)
    kept = T * terms * n
    jacobian = 8.0 * int(n_readings) * P
    jacobian = jacobian if jacobian <= ADJOINT_JACOBIAN_BYTES else 0.0
    products = P
    if not jacobian and P > LOCAL_INFORMATION_ABOVE:   # its compressed products held
        products = LOCAL_INFORMATION_AS_PARAMS
        jacobian = 8.0 * int(n_readings) * LOCAL_COLOURS
    return FitCost(n, P, ADJOINT_BASE_BYTES + ADJOINT_BYTES_PER_TERM * kept
                   + ADJOINT_BYTES_PER_ENTRY * P ** 2 + jacobian,
                   ADJOINT_BASE_S + ADJOINT_SECONDS_PER_WORK * 3 * products * kept, jacobian)


def normal_equations_cost(n_states: int, n_free: int, n_readings: int) -> FitCost:
    """`FitCost` of the normal-equations path (`fitting._normal_equations`) on
    `n_readings` sensor readings over every run: the data's copies, not their Jacobian,
    grow with the log."""
    P, R = int(n_free), int(n_readings)
    return FitCost(int(n_states), P,
                   NORMAL_EQUATIONS_BASE_BYTES + NORMAL_EQUATIONS_BYTES_PER_READING * R,
                   NORMAL_EQUATIONS_BASE_S + NORMAL_EQUATIONS_SECONDS_PER_WORK * R * P ** 2)


def choose_path(n_states: int, n_free: int, eligible: bool, available=None,
                n_samples: int = 0, n_readings: int = 0) -> str:
    """Where the fit may leave the forward path (`eligible`: output error, a linear
    model without bias columns, the default solver): `"normal_equations"` on a long log,
    whose residuals' Jacobian (`n_readings` sensor readings over every run) outweighs the
    network's sensitivities and would take more than `NORMAL_EQUATIONS_ABOVE_BYTES`, or
    the forward path more than `MEMORY_SHARE` of the memory available;
    `"adjoint"` where the forward sensitivities are predicted to take longer than
    `ADJOINT_ABOVE_S`, or to need more than `MEMORY_SHARE` of the memory available where
    the adjoint path needs less (`n_samples` samples over every run: on a long log of a
    small network the adjoint path's kept series need more than the forward path's
    Jacobian); else `"forward"`."""
    if not eligible:
        return "forward"
    cost = fit_cost(n_states, n_free, n_readings)
    available = available_memory() if available is None else available
    too_large = cost.jacobian_bytes > NORMAL_EQUATIONS_ABOVE_BYTES or (
        available is not None and cost.bytes > MEMORY_SHARE * available)
    if too_large and cost.jacobian_bytes > cost.bytes - BASE_BYTES - cost.jacobian_bytes:
        return "normal_equations"
    if available is not None and cost.bytes > MEMORY_SHARE * available:
        adjoint = adjoint_cost(n_states, n_free, n_samples, n_readings=n_readings)
        return "adjoint" if adjoint.bytes < cost.bytes else "forward"
    return "adjoint" if cost.seconds > ADJOINT_ABOVE_S else "forward"


def check_fit_size(n_states: int, n_free: int, source=None, available=None,
                   path: str = "forward", n_samples: int = 0, n_readings: int = 0
                   ) -> FitCost:
    """Refuse (`InputError`) a fit whose predicted memory exceeds `MEMORY_SHARE` of what
    is available (`available` bytes, default now); return its `FitCost`. `path`:
    `choose_path`'s answer (`"adjoint"` costs `adjoint_cost` of `n_samples` samples);
    `n_readings`: the forward path's sensor readings (`fit_cost`)."""
    available = available_memory() if available is None else available
    if path == "normal_equations":  # the data are in memory already: nothing to refuse
        return normal_equations_cost(n_states, n_free, n_readings)
    if path == "adjoint":
        cost = adjoint_cost(n_states, n_free, n_samples, n_readings=n_readings)
        if available is not None and cost.bytes > MEMORY_SHARE * available:
            raise InputError(
                f"fitting {n_free} free parameters of a {n_states}-state network by the "
                f"adjoint path needs about {cost.bytes / 1e9:.1f} GB and "
                f"{available / 1e9:.1f} GB are available. Fix the parameters known from "
                "design (`{ value = ..., fixed = true }`), fit fewer or shorter runs, or "
                "run on a machine with more memory.", file=source)
        return cost
    cost = fit_cost(n_states, n_free, n_readings)
    sensitivities = cost.bytes - BASE_BYTES - cost.jacobian_bytes  # the network's part
    if available is not None and cost.bytes > MEMORY_SHARE * available \
            and cost.jacobian_bytes > sensitivities:
        raise InputError(
            f"fitting {n_free} free parameters to {n_readings:,} sensor readings needs about "
            f"{cost.bytes / 1e9:.1f} GB (the residuals' Jacobian holds readings × free "
            f"parameters numbers, {JACOBIAN_COPIES:g} times over) and "
            f"{available / 1e9:.1f} GB are available. Fit a shorter stretch of the log, or "
            "fewer samples of it (keep every k-th row of the file: the thermal time "
            "constants seldom need every sample), fix the parameters known from design "
            "(`{ value = ..., fixed = true }`), or run on a machine with more memory.",
            file=source)
    if available is not None and cost.bytes > MEMORY_SHARE * available:
        raise InputError(
            f"fitting {n_free} free parameters of a {n_states}-state network needs about "
            f"{cost.bytes / 1e9:.1f} GB (the exact sensitivities grow like P·(2n)²) and "
            f"{available / 1e9:.1f} GB are available. Fix the parameters known from design "
            "(`{ value = ..., fixed = true }`), fit a coarser network (merge nodes of one "
            "body), or run on a machine with more memory.", file=source)
    return cost
