"""`run_montecarlo`: a config, its chunks (resumable, sharded), the report."""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import InputError

#: `THERMOJAX_MONTECARLO_PAUSE=S`: sleep S seconds after each chunk (tests interrupt runs).
_PAUSE = os.environ.get("THERMOJAX_MONTECARLO_PAUSE")

#: `[fit]` keys and defaults: the cap on each unit's trust-region Gauss-Newton steps
#: (`iterations` + 3; a unit stops earlier when it converges), fit the measured bias
#: column too, units in the batch model's pooled fit (0: no batch method), add the
#: end-of-line trim methods (`trim_step`, `trim_sweep`).
FIT_KEYS = {"iterations": 50, "bias_column": True, "batch_units": 0, "trim": False}

#: The per-unit fit's method, hashed into the manifest so that a folder of chunks from
#: another method is never resumed into: 1 = 20 Levenberg-Marquardt + 3 Gauss-Newton
#: steps vmapped over a chunk; 2 = trust-region Gauss-Newton to convergence per unit;
#: 3 = 2 with the secondary-state offset and step-overshoot metrics (and the trim methods).
STUDY_VERSION = 3

PROFILE_KEYS = {"lo": None, "hi": None, "rate": None, "dwell": None, "dt": None,
                "power": 0.0, "start": 25.0}


@dataclass
class MonteCarloConfig:
    path: Path
    spec: object
    model_path: Path
    population: object
    n_units: int
    chunk_size: int
    seed: int
    profile: dict
    bias: str | None
    bias_limit: float
    sensor_noise: bool
    out: str | None
    calibration: dict | None = None
    fit: dict | None = None

    def resolved(self) -> dict:
        """Everything that determines the chunks' contents (hashed into the manifest)."""
        return {"model": str(self.model_path),
                "model_sha256": hashlib.sha256(self.model_path.read_bytes()).hexdigest(),
                "population": _jsonable(self.population.describe()),
                "n_units": self.n_units, "chunk_size": self.chunk_size, "seed": self.seed,
                "profile": self.profile, "bias": self.bias, "sensor_noise": self.sensor_noise,
                "calibration": self.calibration, "fit": self.fit,
                "study_version": STUDY_VERSION}


def _jsonable(x):
    return json.loads(json.dumps(x, default=str))


def _whole(table: dict, key: str, default, minimum: int, file: str,
           where: str | None = None) -> int:
    v = table.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise InputError(f"expected a whole number of at least {minimum}, got {v!r}.",
                         file=file, field=where or key)
    return int(v)


def _num(table: dict, key: str, default, file: str, where: str, positive=False) -> float:
    v = table.get(key, default)
    if v is None:
        raise InputError("missing; give a number.", file=file, field=where)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (
            positive and v <= 0):
        raise InputError(f"expected a {'positive ' if positive else ''}number, got {v!r}.",
                         file=file, field=where)
    return float(v)


def load_config(path) -> MonteCarloConfig:
    """Read and check a Monte Carlo config (docs/cli.md, `thermojax montecarlo`)."""
    from .. import io
    from ._population import population_from_config

    path = Path(path)
    file = str(path)
    try:
        table = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("no such config file.", file=file) from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"not valid TOML ({err}).", file=file) from None
    unknown = set(table) - {"model", "n_units", "chunk_size", "seed", "population", "profile",
                            "calibration", "fit", "spec", "out"}
    if unknown:
        raise InputError(f"unknown key(s) {sorted(unknown)}; expected model, n_units, "
                         "chunk_size, seed, population, profile, calibration, fit, spec, out.",
                         file=file, field=sorted(unknown)[0])
    if "model" not in table:
        raise InputError("missing: the model file (relative to the config) or a built-in "
                         "name.", file=file, field="model")
    model_arg = str(table["model"])
    model_path = (path.parent / model_arg) if not Path(model_arg).is_absolute() else Path(
        model_arg)
    if not model_path.is_file() and Path(model_arg).suffix == "":
        from importlib import resources

        model_path = Path(str(resources.files("thermojax") / "data" / f"{model_arg}.toml"))
    if not model_path.is_file():
        raise InputError(f"no such model file {model_arg!r} (looked beside the config and "
                         "among the built-in models).", file=file, field="model")
    spec = io.load_model(model_path)
    population = population_from_config(spec, table.get("population", {}), file=file)
    profile = _profile(table, "profile", file)
    calibration = _profile(table, "calibration", file) if "calibration" in table else None
    fit_table = table.get("fit", {})
    if not isinstance(fit_table, dict) or set(fit_table) - set(FIT_KEYS):
        raise InputError(f"expected a table with keys {', '.join(FIT_KEYS)}.", file=file,
                         field="fit")
    fit = {"iterations": _whole(fit_table, "iterations", FIT_KEYS["iterations"], 1, file,
                                "fit.iterations"),
           "bias_column": fit_table.get("bias_column", True),
           "batch_units": _whole(fit_table, "batch_units", 0, 0, file, "fit.batch_units"),
           "trim": fit_table.get("trim", False)}
    for key in ("bias_column", "trim"):
        if not isinstance(fit[key], bool):
            raise InputError(f"expected true or false, got {fit[key]!r}.", file=file,
                             field=f"fit.{key}")
    sp = table.get("spec", {})
    if not isinstance(sp, dict) or set(sp) - {"bias", "bias_limit", "sensor_noise"}:
        raise InputError("expected a table with keys bias, bias_limit, sensor_noise.",
                         file=file, field="spec")
    n_units = _whole(table, "n_units", None, 1, file)
    return MonteCarloConfig(
        path=path, spec=spec, model_path=model_path.resolve(), population=population,
        n_units=n_units, chunk_size=min(_whole(table, "chunk_size", 64, 1, file), n_units),
        seed=_whole(table, "seed", 0, 0, file), profile=profile, bias=sp.get("bias"),
        bias_limit=_num(sp, "bias_limit", 0.5, file, "spec.bias_limit", positive=True),
        sensor_noise=bool(sp.get("sensor_noise", True)), out=table.get("out"),
        calibration=calibration, fit=fit)


def _profile(table: dict, key: str, file: str) -> dict:
    prof = table.get(key, {})
    if not isinstance(prof, dict) or set(prof) - set(PROFILE_KEYS):
        raise InputError(f"expected a table with keys {', '.join(PROFILE_KEYS)}.", file=file,
                         field=key)
    profile = {k: _num(prof, k, d, file, f"{key}.{k}",
                       positive=k in ("rate", "dt", "dwell")) for k, d in PROFILE_KEYS.items()}
    if not profile["lo"] < profile["hi"]:
        raise InputError(f"{key}.lo must be below {key}.hi.", file=file, field=f"{key}.lo")
    return profile


def run_montecarlo(config: MonteCarloConfig, out: Path, resume: bool, progress=print) -> dict:
    """Compute every unfinished chunk of this process's share into `out/chunks`, then,
    when every chunk is finished, write `report.json`, `report.md` and plots. Returns
    `{"computed": [...], "skipped": [...], "report": dict | None}`."""
    from ._chunks import ChunkStore, atomic_write_bytes, chunk_units
    from ._population import sample_units, varied_names
    from ._sharding import chunks_of_process, initialize_distributed, process_share, units_mesh

    initialize_distributed()
    index, count = process_share()
    names = varied_names(config.population)
    study = study_of(config)
    store = ChunkStore(out, config.resolved(), config.n_units, config.chunk_size)
    store.open(resume=resume or count > 1)
    fit = config.fit or FIT_KEYS
    mine = chunks_of_process(store.n_chunks, index, count)
    todo = [c for c in mine if not store.is_finished(c)]
    skipped = [c for c in mine if c not in todo]
    if fit["batch_units"] and todo:
        progress(f"fitting the batch model to units {config.n_units}.."
                 f"{config.n_units + fit['batch_units'] - 1} (a sample beside the study's)")
        set_batch_model(study, config)
    mesh = units_mesh()
    share = f" (process {index} of {count})" if count > 1 else ""
    progress(f"{config.n_units} units in {store.n_chunks} chunks of {config.chunk_size}{share}; "
             f"{len(skipped)} finished already, {len(todo)} to compute on "
             f"{mesh.devices.size} device(s) ({mesh.devices.flat[0].platform}); "
             f"{len(study.ts)} samples per unit, the first chunk compiles the study")
    start = time.perf_counter()
    for k, c in enumerate(todo):
        units = chunk_units(config.n_units, config.chunk_size, c)
        # the program's shape is the full chunk size: pad a short last chunk with the
        # next units (deterministic by index), drop their results
        padded = np.arange(units[0], units[0] + config.chunk_size, dtype=np.int64)
        params = sample_units(config.spec, config.population, padded, seed=config.seed)
        metrics = study.compute_chunk(params.log_deviation, padded, config.seed, mesh)
        n = len(units)
        arrays = {"unit": units, "log_deviation": params.log_deviation[:n],
                  "values": params.values[:n], **{k2: v[:n] for k2, v in metrics.items()}}
        store.write(c, arrays)
        if _PAUSE:  # a test aid: time to interrupt a run between chunks
            time.sleep(float(_PAUSE))
        done = k + 1
        rate = done * config.chunk_size / (time.perf_counter() - start)
        bar = "#" * round(20 * done / len(todo))
        progress(f"[{bar:<20}] chunk {c + 1}/{store.n_chunks} written ({done}/{len(todo)} "
                 f"this run, {rate:.1f} units/s)")
    gathered = store.gather()
    report = None
    if gathered is None:
        progress("this process's share is done; other chunks are not finished yet: run again "
                 "with --resume once every process is done, to merge and report")
    else:
        from ._report import write_report

        report = write_report(out, config, gathered, names, study, atomic_write_bytes)
    return {"computed": todo, "skipped": skipped, "report": report}


def study_of(config: MonteCarloConfig):
    """The `Study` of a config, with the population's log-normal prior for the fit."""
    from ._population import log_prior, varied_names
    from ._study import Study

    fit = config.fit or FIT_KEYS
    return Study(config.spec, varied_names(config.population), config.profile,
                 bias=config.bias, sensor_noise=config.sensor_noise, file=str(config.path),
                 prior=log_prior(config.population), calibration=config.calibration,
                 iterations=fit["iterations"], fit_bias=fit["bias_column"],
                 trim=fit.get("trim", False))


def set_batch_model(study, config: MonteCarloConfig):
    """Fit the study's batch model to `fit.batch_units` units drawn after the study's
    own (indices n_units, n_units + 1, ...: the same population and seed, other units)."""
    from ._population import sample_units

    m = (config.fit or FIT_KEYS)["batch_units"]
    sample = sample_units(config.spec, config.population,
                          np.arange(config.n_units, config.n_units + m), seed=config.seed)
    return study.set_batch_model(sample.log_deviation, sample.indices, config.seed)
