"""A `run` config's tables checked before work: `[synthetic]` holds only known keys of the
right kinds, `[options]` numbers are in range, and `name` names one folder inside `out`
(never a path that leaves it, such as "../../../escape")."""

from __future__ import annotations

import math
from pathlib import Path

from .._errors import InputError

SYNTHETIC_KEYS = {"truth", "profiles", "dt", "power", "power_step", "seed"}
MAX_POWER_W = 1e6
MAX_NAME = 200  # characters: the run folder adds a time stamp


def _number(value, path, field: str, *, low: float, high: float, integer: bool = False,
            low_open: bool = False) -> float:
    kind = "a whole number" if integer else "a number"
    ok = (not isinstance(value, bool) and isinstance(value, (int, float))
          and (not integer or isinstance(value, int)) and math.isfinite(value)
          and (value > low if low_open else value >= low) and value <= high)
    if not ok:
        bound = f"above {low:g}" if low_open else f"from {low:g}"
        raise InputError(f"expected {kind} {bound} to {high:g}, got {value!r}.",
                         file=str(path), field=field)
    return value


def check_name(name, path) -> str:
    """A run name: one folder name, no separators, not '.' or '..', not empty."""
    if (not isinstance(name, str) or not name.strip() or name in (".", "..")
            or "/" in name or "\\" in name or "\0" in name or len(name) > MAX_NAME
            or Path(name).name != name):
        raise InputError(f"the run name must be one folder name (no '/', not '.' or '..', at "
                         f"most {MAX_NAME} characters), so the run stays inside `out`; got "
                         f"{name!r}.", file=str(path), field="name")
    return name


def check_synthetic(syn, path) -> None:
    if not isinstance(syn, dict):
        raise InputError(f"expected a table [synthetic], got {syn!r}.", file=str(path),
                         field="synthetic")
    unknown = sorted(set(syn) - SYNTHETIC_KEYS)
    if unknown:
        raise InputError(f"unknown key; [synthetic] may hold {', '.join(sorted(SYNTHETIC_KEYS))}.",
                         file=str(path), field=f"synthetic.{unknown[0]}")
    profiles = syn.get("profiles")
    if (not isinstance(profiles, list) or not profiles
            or not all(isinstance(p, str) for p in profiles)):
        raise InputError(f"expected a non-empty list of built-in profile names, got "
                         f"{profiles!r}.", file=str(path), field="synthetic.profiles")
    if "dt" in syn:
        _number(syn["dt"], path, "synthetic.dt", low=0.0, high=3600.0, low_open=True)
    for key in ("power", "power_step"):
        if key in syn:
            _number(syn[key], path, f"synthetic.{key}", low=-MAX_POWER_W, high=MAX_POWER_W)
    if "seed" in syn:
        _number(syn["seed"], path, "synthetic.seed", low=0, high=2 ** 63 - 1, integer=True)


def check_option_values(options: dict, path) -> None:
    if "perturb" in options:  # a factor: values move by (1 + perturb)^±1
        _number(options["perturb"], path, "options.perturb", low=0.0, high=100.0)
    if "starts" in options:
        _number(options["starts"], path, "options.starts", low=1, high=1000, integer=True)
    if "max_steps" in options:
        _number(options["max_steps"], path, "options.max_steps", low=1, high=100000,
                integer=True)
