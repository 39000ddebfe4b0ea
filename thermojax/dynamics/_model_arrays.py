"""A fitted model's arrays, each from one program compiled once per model structure and
shared by every reader (the score tests, the missing heat): evaluated operation by
operation they compiled a hundred small programs for every model of an investigation."""

from __future__ import annotations

from ..compilation._traced_cache import stored_jit
from ._nonlinear import dataset_states_nonlinear


@stored_jit(once=True)
def linear_parts(model):
    """`(A, B, C, capacitance, offset)` of the model's linear part: (n, n) 1/s, (n, m),
    (p, n), (n,) J/K, and the readings' constant offsets (p,) °C."""
    system = model.linear_system()
    return system.A, system.B, system.C, system.capacitance, model.output_offset()


@stored_jit(once=True)
def free_run_states(model, data, run_initial):
    """Node temperatures (runs, T, n) °C of the model's free run over every run of `data`
    (`dataset_states_nonlinear`)."""
    return dataset_states_nonlinear(model, data, run_initial)
