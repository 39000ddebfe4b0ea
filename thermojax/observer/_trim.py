"""End-of-line trim: a few per-unit scale factors, each on a named group of a model's
parameters, and the observer designed over a grid of them so firmware can adapt its
matrices to the unit at initialisation (docs/observer.md §13: the trim file, the
artifact's section and the C).

A production line cannot afford a full identification per unit, but it can afford a short
test and a few numbers in flash. A factor multiplies every parameter of its group (all
capacitances, the die attach, ...); `thermojax.calibration.estimate_trim` measures the
factors on a unit's end-of-line log, and `trim_design` computes the exact discrete
observer at every point of the factors' grid, which the firmware interpolates once at
start-up (`thermojax.reference.TrimmedObserver`).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import tomllib
from pathlib import Path

import numpy as np

from .._errors import InputError

#: The parameters a factor may scale: the network's, not the noise model's.
TRIMMABLE = ("nodes.*.capacitance", "links.*.conductance", "boundaries.*.conductance",
             "heat_inputs.*.gain")
MAX_GRID_POINTS = 4096   # all factors' grid points together (each one an exact design)


@dataclasses.dataclass(frozen=True)
class TrimFactor:
    """One factor: its `name`, the dotted `parameters` it multiplies (docs/formats.md §5)
    and the factor values `grid` (increasing, two or more) the observer is designed at."""

    name: str
    parameters: tuple[str, ...]
    grid: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class TrimPlan:
    """The factors of an end-of-line trim, in file order."""

    factors: tuple[TrimFactor, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.factors)

    def scaled(self, spec, values):
        """`spec` with every parameter of factor `d` multiplied by `values[d]`."""
        from ..model._parameters_by_name import spec_parameters, with_spec_parameters
        from ..model._spec import Parameter

        params = spec_parameters(spec)
        new = {name: Parameter(params[name].value * float(v), params[name].fixed)
               for f, v in zip(self.factors, values) for name in f.parameters}
        return with_spec_parameters(spec, new)


def load_trim_plan(path: str | Path, spec) -> TrimPlan:
    """Read and check a trim file (docs/observer.md §13) against the model `spec`."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("no such trim file.", file=str(path)) from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"not valid TOML ({err}).", file=str(path)) from None
    return parse_trim_plan(doc, spec, str(path))


def parse_trim_plan(doc: dict, spec, where: str = "<trim>") -> TrimPlan:
    """The `TrimPlan` of a parsed trim file: every pattern matches a trimmable parameter,
    no parameter is in two factors, every range is positive with 2..64 points."""
    from ..model._parameters_by_name import spec_parameters

    unknown = set(doc) - {"factors"}
    if unknown:
        raise InputError(f"unknown key(s) {sorted(unknown)}; a trim file has only "
                         "[[factors]] tables.", file=where)
    tables = doc.get("factors")
    if not isinstance(tables, list) or not tables:
        raise InputError("no [[factors]]: name at least one factor (name, parameters, range, "
                         "points).", file=where, field="factors")
    trimmable = [n for n in spec_parameters(spec)
                 if any(fnmatch.fnmatchcase(n, p) for p in TRIMMABLE)]
    owner: dict[str, str] = {}
    factors = []
    for i, t in enumerate(tables):
        fld = f"factors[{i}]"
        extra = set(t) - {"name", "parameters", "range", "points"}
        if extra:
            raise InputError(f"unknown key(s) {sorted(extra)}; expected name, parameters, "
                             "range, points.", file=where, field=fld)
        name = t.get("name")
        if not isinstance(name, str) or not name.isidentifier():
            raise InputError(f"name must be an identifier (it names a C table entry), got "
                             f"{name!r}.", file=where, field=f"{fld}.name")
        if name in (f.name for f in factors):
            raise InputError(f"two factors are named {name!r}.", file=where, field=f"{fld}.name")
        patterns = t.get("parameters")
        if (not isinstance(patterns, list) or not patterns
                or not all(isinstance(p, str) for p in patterns)):
            raise InputError("parameters must be a list of dotted names or patterns such as "
                             "\"nodes.*.capacitance\".", file=where, field=f"{fld}.parameters")
        names = []
        for pat in patterns:
            hit = [n for n in trimmable if fnmatch.fnmatchcase(n, pat)]
            if not hit:
                raise InputError(f"{pat!r} matches no capacitance, conductance or heat gain of "
                                 f"the model; its trimmable parameters are {trimmable}.",
                                 file=where, field=f"{fld}.parameters")
            names += [n for n in hit if n not in names]
        for n in names:
            if n in owner:
                raise InputError(f"{n} is in factors {owner[n]!r} and {name!r}; a parameter "
                                 "may be scaled by one factor only.", file=where,
                                 field=f"{fld}.parameters")
            owner[n] = name
        rng, points = t.get("range"), t.get("points", 5)
        if (not isinstance(rng, list) or len(rng) != 2
                or not all(isinstance(v, (int, float)) for v in rng)
                or not 0 < rng[0] < 1 < rng[1] or not np.all(np.isfinite(rng))):
            raise InputError(f"range must be [LOW, HIGH] with 0 < LOW < 1 < HIGH (factors "
                             f"around the nominal 1), got {rng!r}.", file=where,
                             field=f"{fld}.range")
        if isinstance(points, bool) or not isinstance(points, int) or not 2 <= points <= 64:
            raise InputError(f"points must be a whole number from 2 to 64, got {points!r}.",
                             file=where, field=f"{fld}.points")
        grid = tuple(float(v) for v in np.linspace(float(rng[0]), float(rng[1]), points))
        factors.append(TrimFactor(name, tuple(names), grid))
    total = int(np.prod([len(f.grid) for f in factors]))
    if total > MAX_GRID_POINTS:
        raise InputError(f"the factors' grid has {total} points (each an exact design, each "
                         f"stored in flash); at most {MAX_GRID_POINTS}: use fewer points.",
                         file=where, field="factors")
    return TrimPlan(tuple(factors))


def _checked_linear(spec, where):
    from ..model._model import ThermalModel
    from ._schedule import refuse_sensor_offsets

    model = ThermalModel.from_spec(spec)
    if model.is_nonlinear:
        raise InputError("the model is nonlinear: the trim scales a linear network's matrices; "
                         "for a linearization that moves with temperature use --schedule.",
                         file=where, field="--trim")
    refuse_sensor_offsets(model, "trimmed", where, "--trim")
    return model


def unit_design(spec, rate_hz: float, plan: TrimPlan, values, where: str = "model") -> dict:
    """The exact observer of one unit, `spec` scaled by `values (D,)`: `Phi (n, n)`,
    `B0`, `B1 (n, m)` discretized exactly at `rate_hz`, the steady-state Kalman gain
    `L (n, p)` of the (unscaled) process and sensor noise, `C (p, n)`, `D (p, m)`."""
    return _design_at(_checked_linear(spec, where), spec, 1.0 / float(rate_hz), plan, values)


def _design_at(model, spec, dt: float, plan: TrimPlan, values) -> dict:
    """`unit_design` with the nominal `model` already built and checked."""
    from ..dynamics._discretize import discretize
    from ..model._model import ThermalModel
    from ._kalman import discrete_process_covariance, steady_state_kalman

    system = ThermalModel.from_spec(plan.scaled(spec, values)).linear_system()
    d = discretize(system, dt)
    Qd = discrete_process_covariance(np.asarray(system.A), np.asarray(model.process_noise), dt)
    L = steady_state_kalman(d, Qd, np.asarray(model.noise, float) ** 2).gain
    return {k: np.asarray(v, float) for k, v in (("Phi", d.Phi), ("B0", d.B0), ("B1", d.B1),
                                                  ("L", L), ("C", system.C), ("D", system.D))}


def trim_design(spec, rate_hz: float, plan: TrimPlan, where: str = "model"):
    """The `thermojax.reference.TrimDesign` of the linear model `spec` at `rate_hz`:
    `unit_design` at every point of the factors' grid (C order, the last factor
    fastest)."""
    from ..reference._trimmed import TrimDesign

    model, dt = _checked_linear(spec, where), 1.0 / float(rate_hz)
    points = [_design_at(model, spec, dt, plan, values)
              for values in itertools.product(*(f.grid for f in plan.factors))]
    return TrimDesign(plan.names, tuple(np.asarray(f.grid) for f in plan.factors),
                      *(np.stack([pt[k] for pt in points]) for k in ("Phi", "B0", "B1", "L")),
                      points[0]["C"], points[0]["D"])
