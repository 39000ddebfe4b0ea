"""`thermojax calibrate CONFIG`: the calibration pipeline's named stages into a fresh
results folder (docs/formats.md §5, docs/cli.md). Edges only."""

from __future__ import annotations

from pathlib import Path

from .._errors import InputError
from ._outputs import check_output_folder, claim_output_folder, staged_folder


def cmd_calibrate(args) -> int:
    from ..calibration._pipeline import prepare, run_pipeline
    from ..calibration._report import write_results

    if args.make_example_data is not None:
        from ..calibration._synthetic import synthetic_imu_logs, write_example_config

        out = Path(args.make_example_data)
        claim_output_folder(out)  # one writer at a time, and room for the logs
        args.progress(f"simulating the example runs (truth: configs/imu6_bias.toml) into {out}")
        runs = synthetic_imu_logs(out)
        for r in runs.values():
            print(f"wrote {r.temperature_file}")
            print(f"wrote {r.inertial_file}")
        config = write_example_config(out)
        print(f"wrote {config} and {config.with_name('imu6_bias_start.toml')}; next: "
              f"thermojax calibrate {config}")
        return 0
    if args.config is None:
        raise InputError("name a calibration config (or --make-example-data DIR).",
                         field="CONFIG")
    config_path = Path(args.config)
    out = Path(args.out) if args.out else config_path.with_suffix("").with_name(
        config_path.stem + "_results")
    check_output_folder(out, args.force)
    config, _, _ = prepare(config_path)  # every check before any work
    args.progress(f"calibrating {', '.join(config.channels)} with the stages "
                  f"{', '.join(config.stages)}")
    with staged_folder(out) as tmp:
        res = run_pipeline(config, observer_dir=tmp / "observer" if "verify" in config.stages
                           else None, progress=args.progress)
        written = write_results(res, tmp)
    for name in written:
        print(f"  {out / name}")
    if res.observer_dir is not None:
        print(f"  {out / 'observer'}")
    if res.passed is not None:
        for ch in res.checks:
            print(f"{ch.run} {ch.channel}: residual RMS {ch.rms:.4g}, peak {ch.peak:.4g} "
                  f"(spec {ch.limits}): {'PASS' if ch.passed else 'FAIL'}")
        print(f"verification {'PASSED' if res.passed else 'FAILED'}")
    print(f"results in {out}")
    return 0


def add_calibrate(sub):
    from ._arguments import _add_force, _add_quiet

    p = sub.add_parser("calibrate", help="run the calibration pipeline of a config",
                       description="Run the calibration pipeline's named stages (condition, "
                       "static_polynomial, thermal_fit, coupling, verify) of a config TOML and "
                       "write a fresh results folder: report.json, report.md, "
                       "model_calibrated.toml, the exported observer and plots. See "
                       "docs/cli.md for the config format.")
    p.add_argument("config", nargs="?", default=None, help="calibration config TOML")
    p.add_argument("--out", default=None,
                   help="results folder (default: CONFIG's name with _results, beside it)")
    p.add_argument("--make-example-data", metavar="DIR", default=None,
                   help="only write the example's synthetic logs (configs/imu6_bias.toml "
                   "truth) into DIR, with the example config DIR/imu6_bias.toml that reads "
                   "them (also for configs/calibration/imu6_bias.toml: DIR = "
                   "configs/calibration/data)")
    _add_force(p, "an existing --out folder")
    _add_quiet(p)
    p.set_defaults(func=cmd_calibrate)
