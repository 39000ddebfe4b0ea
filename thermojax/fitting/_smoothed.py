"""The Kalman likelihood's smoothed node temperatures (RTS), one program for every run.

On its own so that `FitResult.smoothed` (`_fit_result`) and the Kalman fit that compiles
it ahead (`_kalman_fit`) both import it without importing each other.
"""

from __future__ import annotations

from ..compilation._traced_cache import stored_jit
from ._likelihood import kalman_runs, rts_smoother


@stored_jit(once=True)
def kalman_smoothed(model, data, run_initial):
    """RTS-smoothed node temperatures of every run: mean and std, each (runs, times,
    states) °C."""
    return kalman_runs(model, data, run_initial, lambda ts, kf: rts_smoother(model, ts, kf))
