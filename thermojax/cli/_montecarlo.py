"""`thermojax montecarlo CONFIG`: the unit-variance study in resumable chunks
(docs/formats.md §5, docs/cli.md). Edges only."""

from __future__ import annotations

import os
from pathlib import Path

from .._errors import InputError
from ._outputs import check_output_folder, is_own_folder, mark_own


def cmd_montecarlo(args) -> int:
    from ..montecarlo import load_config, run_montecarlo

    from ..montecarlo._size import check_study_size

    config = load_config(args.config)
    check_study_size(config)  # before the folder is claimed or any unit drawn
    out = Path(args.out or config.out or f"montecarlo_{Path(args.config).stem}")
    check_output_folder(out, args.force, in_place=True, shared=_shared_lock_key())
    if out.is_dir() and is_own_folder(out) and (out / "manifest.json").is_file() and not (
            args.resume or args.force):
        raise InputError("the folder holds chunks of an earlier run; pass --resume to "
                         "continue it or --force to start afresh.", file=str(out),
                         field="--out")
    mark_own(out)
    result = run_montecarlo(config, out, resume=args.resume and not args.force,
                            progress=args.progress)
    report = result["report"]
    if report is None:
        print(f"computed {len(result['computed'])} chunk(s) into {out / 'chunks'}; the "
              "others are not finished (another process's share): run again with --resume "
              "to merge")
        return 0
    u = report["bias_units"]
    print(f"{report['n_units']} units; bias channel {report['bias_channel']}, specification "
          f"±{report['bias_limit']:g} {u} (peak over the profile)")
    for m, label in report["methods"].items():
        b = report["percentiles"][m]["bias_peak"]
        t = report["percentiles"][m]["temp_peak"]
        print(f"  {label}: {100 * report['fraction_within_bias_spec'][m]:.1f} % within spec; "
              f"bias peak p50 {b['p50']:.3g}, p95 {b['p95']:.3g}, max {b['max']:.3g} {u}; "
              f"{report['temperature_node']} estimate peak p95 {t['p95']:.3g} K")
    if report["sensitivity"]:
        top = report["sensitivity"][0]
        print(f"  the spread that matters most: {top['parameter']} "
              f"({top['coefficient_per_sd']:+.3g} {u} per standard deviation)")
    print(f"wrote {out / 'report.json'}, {out / 'report.md'} and plots "
          f"({len(result['computed'])} chunk(s) computed, {len(result['skipped'])} resumed)")
    return 0


def _shared_lock_key() -> str | None:
    """None for a study one process computes (the folder locked whole); for one sharded
    over processes (docs/cli.md), each process's own lock key, since they fill one
    folder together (`process<i>`, or no key of its own where the index is not known
    before JAX starts: then the lock is this process's alone)."""
    env = os.environ
    if not any(env.get(v) for v in ("THERMOJAX_PROCESS_COUNT", "THERMOJAX_PROCESS_INDEX",
                                     "THERMOJAX_DISTRIBUTED", "JAX_COORDINATOR_ADDRESS",
                                     "JAX_NUM_PROCESSES")):
        return None
    index = env.get("THERMOJAX_PROCESS_INDEX") or env.get("JAX_PROCESS_ID")
    return f"process{index}" if index is not None else f"pid{os.getpid()}"


def add_montecarlo(sub):
    from ._arguments import _add_force, _add_quiet

    p = sub.add_parser("montecarlo", help="unit-variance Monte Carlo study, in resumable chunks",
                       description="Sample a population of units (the config's preset, "
                       "spreads, correlated groups and die-attach voids), simulate each unit's "
                       "calibration and test runs, identify it from its calibration run "
                       "(batched MAP fits, the population as prior) and compensate its test "
                       "run with the nominal model, a batch model (fit.batch_units), its "
                       "fitted model and its true model. Units are computed in chunks sharded over every local "
                       "device, each chunk written atomically; --resume continues an "
                       "interrupted run. Writes DIR/report.json, DIR/report.md and "
                       "distribution plots.")
    p.add_argument("config", help="Monte Carlo config TOML (configs/montecarlo/*.toml)")
    p.add_argument("--out", default=None,
                   help="output folder (default: the config's `out`, else montecarlo_<config "
                   "name>)")
    p.add_argument("--resume", action="store_true",
                   help="keep the finished chunks of an interrupted run of the same config "
                   "and compute the rest (refused for a folder of another config)")
    _add_force(p, "an existing --out folder (and start afresh)")
    _add_quiet(p)
    p.set_defaults(func=cmd_montecarlo)
