"""Config-driven experiments: `thermojax run CONFIG.toml`.

A config names a model, the data (CSV files, or synthetic runs simulated from a
"truth" model through built-in chamber profiles), the likelihood and options.
Each run writes a new folder `<out>/<name>-<UTC time>[-<n>]` holding the
resolved config, the package versions and the fit's outputs; it never
overwrites an earlier run.

```toml
name = "imu6_three_ramps"
model = "../imu6.toml"             # paths are relative to this file
likelihood = "output_error"        # or "kalman"
out = "../../results"              # parent folder of the run folders

data = ["run1.csv", "run2.csv"]    # either CSV files ...

[synthetic]                        # ... or runs simulated from a truth model
truth = "../imu6.toml"
profiles = ["ramp1", "ramp5", "ramp10"]
dt = 1.0
power = 0.05                       # W on every heat input, plus the profile's own
power_step = 0.05                  # W added between 30 and 60 min (makes C and G separable)
seed = 0

[options]
starts = 1
perturb = 0.3                      # start every free parameter this far off (relative)
outliers = "stop"                  # or "drop": as `fit --outliers`
interval_check = true              # false: as `fit --no-interval-check`
```
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import platform
import tomllib
from importlib import metadata
from pathlib import Path

import numpy as np

from .._errors import InputError
from ._config_checks import check_name, check_synthetic

_KEYS = {"name", "model", "likelihood", "out", "data", "synthetic", "options"}
_OPTIONS = {"starts", "perturb", "max_steps", "outliers", "interval_check"}


def check_options(options: dict, path: str | Path) -> None:
    """Raise `InputError` on an unknown or ill-typed `[options]` entry of config `path`."""
    if set(options) - _OPTIONS:
        raise InputError(f"unknown option(s) {sorted(set(options) - _OPTIONS)}; allowed "
                         f"are {sorted(_OPTIONS)}.", file=str(path), field="options")
    if options.get("outliers", "stop") not in ("stop", "drop"):
        raise InputError(f"options.outliers must be \"stop\" or \"drop\", got "
                         f"{options['outliers']!r}.", file=str(path), field="options.outliers")
    from ._config_checks import check_option_values

    check_option_values(options, path)
    if not isinstance(options.get("interval_check", True), bool):
        raise InputError(f"options.interval_check must be true or false, got "
                         f"{options['interval_check']!r}.", file=str(path),
                         field="options.interval_check")


def load_config(path: str | Path) -> dict:
    """Read and resolve a run config (paths made absolute). Raises `InputError`."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("config file not found.", file=str(path)) from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"TOML syntax error: {err}.", file=str(path)) from None
    unknown = set(raw) - _KEYS
    if unknown:
        raise InputError(f"unknown key(s) {sorted(unknown)}; allowed are {sorted(_KEYS)}.",
                         file=str(path), field=sorted(unknown)[0])
    for key in ("model",):
        if key not in raw:
            raise InputError(f"missing required key '{key}'.", file=str(path), field=key)
    if ("data" in raw) == ("synthetic" in raw):
        raise InputError("give either `data = [...]` (CSV files) or a [synthetic] table, not "
                         "both or neither.", file=str(path), field="data")
    base = path.parent.resolve()

    def resolve(p: str, fld: str) -> str:
        if not isinstance(p, str):
            raise InputError(f"expected a path string, got {p!r}.", file=str(path), field=fld)
        q = Path(p)
        return str(q if q.is_absolute() else (base / q).resolve())

    cfg = {
        "name": check_name(raw.get("name", path.stem), path),
        "config_file": str(path.resolve()),
        "model": resolve(raw["model"], "model"),
        "likelihood": raw.get("likelihood", "output_error"),
        "out": resolve(raw.get("out", "results"), "out"),
        "options": dict(raw.get("options", {})),
    }
    check_options(cfg["options"], path)
    if "data" in raw:
        if not isinstance(raw["data"], list) or not raw["data"]:
            raise InputError("data must be a non-empty list of CSV paths.", file=str(path),
                             field="data")
        cfg["data"] = [resolve(p, "data") for p in raw["data"]]
    else:
        syn = raw["synthetic"]
        if not isinstance(syn, dict) or "truth" not in syn or "profiles" not in syn:
            raise InputError("[synthetic] needs `truth` (a model file) and `profiles` (built-in "
                             "profile names).", file=str(path), field="synthetic")
        check_synthetic(syn, path)
        syn = dict(syn)
        syn["truth"] = resolve(syn["truth"], "synthetic.truth")
        cfg["synthetic"] = syn
    return cfg


def new_run_folder(parent: Path, name: str) -> Path:
    """A folder that did not exist before: `<parent>/<name>-<UTC time>[-n]`."""
    from ._outputs import ROOM_FOLDER, check_room

    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    parent.mkdir(parents=True, exist_ok=True)
    check_room(parent, ROOM_FOLDER)  # before the work, not after it
    for n in range(1000):
        folder = parent / (f"{name}-{stamp}" + (f"-{n}" if n else ""))
        try:
            folder.mkdir()
            return folder
        except FileExistsError:
            continue
    raise InputError("could not create a new run folder.", file=str(parent))


def package_versions() -> dict:
    out = {"python": platform.python_version()}
    for pkg in ("thermojax", "jax", "jaxlib", "equinox", "optimistix", "diffrax", "lineax",
                "numpy", "scipy", "matplotlib"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def synthetic_runs(spec, syn: dict, folder: Path) -> list[str]:
    """Simulate the truth model through built-in profiles (with sensor noise); write CSVs."""
    from .. import io
    from .. import ThermalNetwork  # noqa: F401  (switches JAX to float64 first)
    from ..dynamics._as_written import simulate_as_written

    truth = io.load_model(syn["truth"])
    rng = np.random.default_rng(int(syn.get("seed", 0)))
    paths = []
    for i, name in enumerate(syn["profiles"]):
        prof = io.load_profile(name, dt=float(syn.get("dt", 1.0)))
        u = io.profile_inputs(truth, prof, float(syn.get("power", 0.0)))
        step = float(syn.get("power_step", 0.0))
        heat = [j for j, c in enumerate(truth.input_columns) if c in truth.heat_columns]
        u[:, heat] += step * ((prof.ts >= 1800) & (prof.ts < 3600))[:, None]
        y = simulate_as_written(truth, np.asarray(prof.ts, float), u).outputs  # effects too
        stds = np.array([s.noise.value if s.noise is not None else 0.01 for s in truth.sensors])
        y = y + rng.standard_normal(y.shape) * stds
        channels = {c: u[:, j] for j, c in enumerate(truth.input_columns)}
        channels.update({c: y[:, j] for j, c in enumerate(truth.sensor_columns)})
        p = folder / f"synthetic_{i}_{name}.csv"
        io.write_telemetry(p, prof.ts, channels,
                           comments=[f"synthetic run from {syn['truth']}, profile {name}"])
        paths.append(str(p))
    return paths


def perturbed(spec, factor: float, seed: int = 0):
    """`spec` with every free capacitance, conductance and gain moved by ±`factor`."""
    from ..model._spec import Parameter

    rng = np.random.default_rng(seed)

    def move(p: Parameter) -> Parameter:
        if p.fixed:
            return p
        return Parameter(p.value * (1 + factor) ** rng.choice([-1.0, 1.0]), False)

    return spec.replace(
        nodes=tuple(dataclasses.replace(n, capacitance=move(n.capacitance)) for n in spec.nodes),
        links=tuple(dataclasses.replace(k, conductance=move(k.conductance)) for k in spec.links),
        boundaries=tuple(dataclasses.replace(b, conductance=move(b.conductance))
                         for b in spec.boundaries),
        heat_inputs=tuple(dataclasses.replace(h, gain=move(h.gain)) for h in spec.heat_inputs))


def run_config(path: str | Path, progress=print, out: str | Path | None = None,
               options: dict | None = None) -> Path:
    """Run one config; return the new results folder (under `out` when given, else
    under the config's own `out`). `options` replace entries of the config's
    `[options]` (as a study's command-line flags do)."""
    from .. import io
    from ..fitting._fit_report import comparison_table, write_fit_outputs
    from ..fitting._interval_check import check_intervals
    from ._checked_runs import fit_dropping, load_runs

    cfg = load_config(path)
    if options:
        cfg["options"].update(options)
        check_options(cfg["options"], path)
    spec = io.load_model(cfg["model"])
    opts = cfg["options"]
    outliers = opts.get("outliers", "stop")
    # the runs checked (and refused) before a folder is made
    loaded = load_runs(spec, cfg["data"], outliers) if "data" in cfg else None
    folder = new_run_folder(Path(out if out is not None else cfg["out"]), cfg["name"])
    (folder / "versions.json").write_text(json.dumps(package_versions(), indent=2))
    if "synthetic" in cfg:
        progress(f"simulating {len(cfg['synthetic']['profiles'])} synthetic runs")
        data = synthetic_runs(spec, cfg["synthetic"], folder)
    else:
        data = cfg["data"]
    cfg["resolved_data"] = data
    (folder / "config.json").write_text(json.dumps(cfg, indent=2))
    experiments, telemetry, dropped = loaded or load_runs(spec, data, outliers)
    if "perturb" in opts:
        spec = perturbed(spec, float(opts["perturb"]))
    result, experiments = fit_dropping(
        spec, experiments, telemetry, dropped, outliers, progress,
        likelihood=cfg["likelihood"], n_starts=int(opts.get("starts", 1)),
        max_steps=int(opts.get("max_steps", 200)), smoothed=True)
    profiles = (check_intervals(result, progress)  # as `fit` does (output error)
                if opts.get("interval_check", True) else {})
    write_fit_outputs(result, experiments, folder, data, profiles, dropped=dropped)
    progress(comparison_table(result))
    return folder
