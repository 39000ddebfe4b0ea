"""Telemetry made ready for a fit: each run checked for plausibility against the model
(`--outliers`, `measurements/_plausibility.py`), and the fit repeated without a sample
that alone decided it (`fitting/_dominance.py`). Every dropped cell is said on stderr
and kept for `report.json` (`dropped_cells`)."""

from __future__ import annotations

import sys

MAX_DROP_ROUNDS = 3  # refits after leaving out samples that alone decided the fit


def read_runs(paths: list[str]):
    """The telemetry of each `--data` file; the same file (or the same bytes) given twice
    is refused: counted twice, it would make every std √2 too small."""
    import hashlib
    import os

    from .._errors import InputError
    from ..measurements._telemetry import read_telemetry

    seen: dict[tuple, str] = {}
    for p in paths:
        try:
            with open(p, "rb") as f:
                digest = hashlib.sha256(f.read(1 << 26)).hexdigest()  # the first 64 MiB
            key = (digest, os.path.getsize(p))
        except OSError:
            continue  # read_telemetry names the problem
        if key in seen:
            same = os.path.realpath(p) == os.path.realpath(seen[key])
            raise InputError(
                f"--data {p} is {'the same file as' if same else 'a copy of'} --data "
                f"{seen[key]}: every run must be a different measurement (counted twice, a "
                "run would make every std √2 too small). Give each file once.",
                file=p, field="--data")
        seen[key] = p
    return [read_telemetry(p) for p in paths]


def checked(spec, runs, outliers: str = "stop", others: bool = False):
    """Each run checked (`others`: the columns the model does not read too, as candidate
    inputs), its drops said: `[(telemetry, [Outlier])]`."""
    from ..measurements._plausibility import check_plausibility, describe_dropped

    out = [check_plausibility(spec, t, outliers, others=others) for t in runs]
    for t, dropped in out:
        if dropped:
            print(f"warning: {describe_dropped(t, dropped)}", file=sys.stderr)
    return out


def plausible(spec, runs, outliers: str = "stop", others: bool = False):
    """The runs of `checked`, without the list of drops."""
    return [t for t, _ in checked(spec, runs, outliers, others)]


def load_runs(spec, paths: list[str], outliers: str = "stop"):
    """`(experiments, telemetry, dropped)`: the runs in `paths` checked, their telemetry
    and the cells dropped, one dict each (`file`, `line`, `column`, `value`, `reason`)."""
    from ..measurements._data import Experiment

    runs = checked(spec, read_runs(paths), outliers)
    dropped = [{"file": p, "line": o.line, "column": o.column, "value": o.value,
                "reason": o.reason} for p, (_, found) in zip(paths, runs) for o in found]
    telemetry = [t for t, _ in runs]
    return ([Experiment.from_telemetry(spec, t, name=p) for p, t in zip(paths, telemetry)],
            telemetry, dropped)


def fit_dropping(spec, experiments, telemetry, dropped: list[dict], outliers: str, say,
                 **fit_options):
    """`fit(spec, experiments, **fit_options)`, then, with `outliers="drop"`, again
    without the samples that alone decided it, at most `MAX_DROP_ROUNDS` times; each
    dropped sample is said and appended to `dropped`. Returns `(result, experiments)`."""
    from ..fitting._dominance import without_samples
    from ..fitting._fit import fit

    result = fit(spec, experiments, progress=say, **fit_options)
    for _ in range(MAX_DROP_ROUNDS):
        if outliers != "drop" or not result.dominant:
            break
        for d in result.dominant:
            line = int(telemetry[d.run].lines[d.row])
            print(f"warning: {d.run_name}: dropped line {line}, column '{d.column}' = "
                  f"{d.value:.6g}: a glitch the fit followed, carrying {100 * d.share:.0f} % "
                  "of the column's squared error (--outliers drop); refitting",
                  file=sys.stderr)
            dropped.append({"file": d.run_name, "line": line, "column": d.column,
                            "value": d.value, "reason": f"carried {100 * d.share:.0f} % of "
                            "the column's squared error in the fit"})
        experiments = without_samples(experiments, result.dominant, spec.sensor_columns)
        result = fit(spec, experiments, progress=say, **fit_options)
    return result, experiments
