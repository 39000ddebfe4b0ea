"""`thermojax trim`: a unit's end-of-line trim factors from its test log (docs/cli.md,
docs/observer.md §13). Edges only."""

from __future__ import annotations

import json
from pathlib import Path

from ._outputs import check_output_folder, staged_folder


def cmd_trim(args) -> int:
    from ..calibration._plots import plot_trim
    from ..calibration._trim import estimate_trim, trim_outputs
    from ..io import load_model
    from ..observer._trim import load_trim_plan
    from ._checked_runs import load_runs
    from ._arguments import _resolve_model

    out = Path(args.out)
    check_output_folder(out, args.force)
    spec = load_model(_resolve_model(args.model))
    plan = load_trim_plan(args.factors, spec)
    experiments, _, dropped = load_runs(spec, args.data, args.outliers)
    args.progress(f"estimating {', '.join(plan.names)} from {len(experiments)} log(s)")
    est = estimate_trim(spec, experiments, plan)
    record = {"model": str(args.model), "trim_file": str(args.factors),
              "logs": list(args.data), **est.as_dict(),
              "parameters": {f.name: list(f.parameters) for f in plan.factors},
              "dropped_cells": dropped}
    with staged_folder(out) as tmp:
        (tmp / "trim.json").write_text(json.dumps(record, indent=2, allow_nan=False) + "\n")
        for i, e in enumerate(experiments):
            plot_trim(tmp / f"trim_run{i}.png", e.ts, e.outputs,
                      trim_outputs(spec, e, plan, [1.0] * len(plan.factors)),
                      trim_outputs(spec, e, plan, est.values), spec.sensor_columns,
                      f"{Path(e.name).name}: nominal against trimmed")
    for name, v, s in zip(est.names, est.values, est.std):
        print(f"{name}: {v:.6g} ± {s:.2g}")
    for col, a, b in zip(est.sensors, est.rmse_nominal, est.rmse_trimmed):
        print(f"{col}: RMSE {a:.4g} °C nominal, {b:.4g} °C trimmed")
    if not est.converged:
        print("warning: the least-squares solve did not converge, or the log does not "
              "determine a factor (its std is null or above a factor of e): do not use these "
              "factors; test with a profile that excites what each factor scales.")
    print(f"results in {out} (next: thermojax export ... --trim {args.factors} "
          f"--trim-factors {out / 'trim.json'})")
    return 0 if est.converged else 1


def add_trim(sub):
    from ._arguments import _add_force, _add_quiet

    p = sub.add_parser("trim", help="a unit's end-of-line trim factors from its test log",
                       description="Estimate a unit's end-of-line scale factors (the trim file's "
                       "[[factors]], each multiplying a group of the model's parameters) from "
                       "its short test log(s), the rest of the model nominal. Writes "
                       "DIR/trim.json (factors ± std, RMSE nominal and trimmed) and a plot per "
                       "log; export --trim --trim-factors puts them into the observer.")
    p.add_argument("--model", required=True, help="model TOML file or built-in model name")
    p.add_argument("--factors", required=True, metavar="TRIM.toml",
                   help="the trim file: the factors and their grids (docs/observer.md §13)")
    p.add_argument("--data", required=True, action="append",
                   help="the unit's end-of-line telemetry CSV (repeatable)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--outliers", choices=["stop", "drop"], default="stop",
                   help="an implausible cell: stop (default) or drop it")
    _add_force(p, "an existing --out folder")
    _add_quiet(p)
    p.set_defaults(func=cmd_trim)
