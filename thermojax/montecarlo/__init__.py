"""Unit-variance Monte Carlo: populations of units, the study (nominal, batch-level,
per-unit fitted and own models), and resumable chunked runs sharded over devices and
processes."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._chunks import ChunkStore, atomic_write_bytes, config_hash
from ._population import (PRESETS, Population, UnitParameters, Voids, log_prior,
                          population_from_config, preset_population, sample_units,
                          varied_names)
from ._run import MonteCarloConfig, load_config, run_montecarlo, study_of
from ._sharding import chunks_of_process, process_share, shard_units, units_mesh
from ._gain_doubling import kalman_gain_doubling
from ._study import METHODS, Study, profile_inputs, ramp_profile
from ._summary import sensitivity, summarize

__all__ = [
    "ChunkStore", "METHODS", "MonteCarloConfig", "PRESETS", "Population", "Study",
    "UnitParameters", "Voids", "atomic_write_bytes", "chunks_of_process", "config_hash",
    "kalman_gain_doubling", "load_config", "log_prior", "population_from_config",
    "preset_population", "process_share", "profile_inputs", "ramp_profile", "run_montecarlo",
    "sample_units", "sensitivity", "shard_units", "study_of", "summarize", "units_mesh",
    "varied_names",
]
