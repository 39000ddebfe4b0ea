"""A Monte Carlo study's memory, predicted from its config and refused before any work
when it cannot fit: the gathered results grow with `n_units`, one chunk's simulation with
`chunk_size` times the samples of its runs (a config with `n_units = 1e9` is refused in
milliseconds instead of growing until the machine stops it)."""

from __future__ import annotations

from .._sizes import check_memory

#: Bytes of gathered results per unit and per varied parameter (deviation and value),
#: plus a fixed share for the metrics, with copies for the report's statistics.
RESULT_BYTES_PER_PARAMETER = 2 * 8 * 3
RESULT_BYTES_FIXED = 64 * 8 * 3
#: Bytes per unit, per sample and per state of one chunk's simulation, fit and observers
#: (states and their sensitivities in float64, twice).
CHUNK_BYTES_PER_CELL = 16


def run_samples(profile: dict | None) -> float:
    """Samples of one run of a profile table (lo, hi, rate °C/min, dwell s, dt s): about
    three ramps across the span and three dwells."""
    if not profile:
        return 0.0
    span = 3 * (profile["hi"] - profile["lo"]) / (profile["rate"] / 60.0) + 3 * profile["dwell"]
    return span / profile["dt"]


def predicted_bytes(config) -> float:
    from ._population import varied_names

    n_varied = len(varied_names(config.population))
    n_states = len(config.spec.nodes) + len(config.spec.effects)
    results = config.n_units * (RESULT_BYTES_PER_PARAMETER * n_varied + RESULT_BYTES_FIXED)
    samples = run_samples(config.profile) + run_samples(config.calibration)
    chunk = (config.chunk_size * samples * max(n_states, 1) * (n_varied + 2)
             * CHUNK_BYTES_PER_CELL)
    return results + chunk


def check_study_size(config) -> float:
    """Refuse a study whose predicted memory cannot fit; return the prediction (bytes)."""
    need = predicted_bytes(config)
    check_memory(need, f"{config.n_units} units in chunks of {config.chunk_size}",
                 fix="Lower n_units (or chunk_size), or run the study in shards.",
                 file=str(config.path), field="n_units")
    return need
