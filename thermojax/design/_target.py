"""The shortest designed profile that reaches given standard errors.

The duration is searched on a grid of `steps` lengths up to the longest allowed,
`D_k = k · D_max / steps` (rounded to whole sample periods), by bisection: a profile is
designed at each length tried, and the length is enough when every named parameter's
predicted relative std is at or below its target. Longer profiles of the same design
family do at least as well as shorter ones in practice (a longer profile can repeat a
shorter one and add to it), which is what bisection assumes; every length tried is
reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .._errors import InputError
from ..model._spec import ModelSpec
from ._design import Design, design


@dataclass
class TargetSearch:
    """The result of `shortest_design`: the design kept (the shortest that met the targets,
    else the longest tried), whether it met them, and every length tried as
    `(duration_s, met, {name: predicted relative std})`."""

    design: Design
    met: bool
    targets: dict[str, float]
    tried: list = field(default_factory=list)


def shortest_design(spec: ModelSpec, max_duration_s: float, targets: dict[str, float], *,
                    dt: float = 1.0, steps: int = 8, criterion: str | None = None,
                    progress=None, **kwargs) -> TargetSearch:
    """Design the shortest profile, up to `max_duration_s`, whose predicted relative std of
    each parameter named in `targets` (name -> relative std, e.g. 0.01 for 1 %) is at most
    its target. `criterion`: default the variance of the targeted parameters. Other
    arguments go to `design`."""
    say = progress or (lambda *a, **k: None)
    if not targets:
        raise InputError("--target-std needs at least one NAME=STD.", field="--target-std")
    for name, value in targets.items():
        if not (value > 0):
            raise InputError(f"the target std of {name} must be > 0 (a relative std: 0.01 "
                             "is 1 %).", field="--target-std")
    criterion = criterion or "variance"
    params = list(targets) if criterion == "variance" else None
    periods = int(round(max_duration_s / dt))
    lengths = sorted({max(2, int(round(periods * k / steps))) * dt for k in range(1, steps + 1)})
    cache: dict[float, Design] = {}

    def judge(length: float):
        if length not in cache:
            say(f"designing {length:g} s")
            cache[length] = design(spec, length, dt=dt, criterion=criterion, parameters=params,
                                   progress=progress, **kwargs)
        d = cache[length]
        unknown = [n for n in targets if n not in d.designed.stds]
        if unknown:
            raise InputError(f"'{unknown[0]}' is not a free parameter of the model; free ones "
                             f"are {', '.join(d.designed.stds)}.", file=spec.source,
                             field="--target-std")
        stds = {n: d.designed.stds[n] for n in targets}
        met = all(s is not None and s <= targets[n] for n, s in stds.items())
        return met, stds

    tried = []
    lo, hi = 0, len(lengths) - 1
    met_hi, stds = judge(lengths[hi])
    tried.append((lengths[hi], met_hi, stds))
    if not met_hi:
        return TargetSearch(cache[lengths[hi]], False, dict(targets), tried)
    best = hi
    while lo < best:
        mid = (lo + best) // 2
        met, stds = judge(lengths[mid])
        tried.append((lengths[mid], met, stds))
        if met:
            best = mid
        else:
            lo = mid + 1
    return TargetSearch(cache[lengths[best]], True, dict(targets), sorted(tried))
