"""`thermojax design --model M --duration D --out DIR`: the chamber profile that best
determines the model's parameters within the chamber's limits. Edges only; the work is
`design/`."""

from __future__ import annotations

import argparse
from pathlib import Path

from .._errors import InputError
from ._arguments import _add_force, _add_quiet, _positive_float, _positive_int, _resolve_model


def _duration(text: str) -> float:
    """A duration: seconds (`14400`), or with a unit `s`, `min` or `h` (`4h`, `90min`)."""
    t = text.strip().lower()
    for unit, scale in (("min", 60.0), ("h", 3600.0), ("s", 1.0)):
        if t.endswith(unit):
            t, factor = t[: -len(unit)].strip(), scale
            break
    else:
        factor = 1.0
    try:
        value = float(t) * factor
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a duration such as 14400, 4h or 90min, "
                                         f"got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite duration > 0, got {text!r}")
    return value


def _pair(text: str) -> tuple[float, float]:
    """`LOW,HIGH`: two finite numbers."""
    parts = text.split(",")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH (two numbers), got {text!r}"
                                         ) from None
    return lo, hi


def cmd_design(args) -> int:
    from .. import io
    from ..design import design, write_design
    from ._outputs import check_output_folder, staged_folder

    out = Path(args.out)
    check_output_folder(out, args.force)
    if args.from_investigation:
        if args.rivals:
            raise InputError("--from-investigation takes its rivals from the investigation; "
                             "drop --rivals.", field="--rivals")
        return _discriminate(args, None, _limits(args), out)
    if args.model is None:
        raise InputError("--model is required (or --from-investigation DIR).", field="--model")
    model_path = _resolve_model(args.model)
    spec = io.load_model(model_path)
    limits = _limits(args)
    _check_names(spec, [(n, "--parameter") for n in args.parameter or []]
                 + [(n, "--target-std") for n, _ in args.target_std or []])
    if args.target_std:
        return _shortest(args, spec, limits, out)
    args.criterion = args.criterion or "d"
    if args.criterion == "variance" and not args.parameter:
        raise InputError("the variance criterion needs at least one --parameter NAME (a free "
                         "parameter's dotted name, as fit's report.json names it).",
                         field="--parameter")
    if args.parameter and args.criterion != "variance":
        raise InputError("--parameter names the parameters of the variance criterion; add "
                         "--criterion variance.", field="--parameter")
    if args.rivals:
        return _discriminate(args, spec, limits, out)
    result = design(spec, args.duration, limits=limits, dt=args.dt, criterion=args.criterion,
                    parameters=args.parameter, n_starts=args.starts or 4,
                    temperature_segments=args.knots, power_segments=args.power_steps,
                    noise=args.noise, progress=args.progress)
    with staged_folder(out) as tmp:
        report = write_design(result, tmp, str(args.model))
    refs = list(report["references"])
    print(f"{'parameter':<44} {'designed':>10} " + " ".join(f"{r:>12}" for r in refs))
    for p, s in report["designed"]["stds"].items():
        cells = [_pct(s["relative_std"])] + [
            _pct(report["references"][r]["stds"][p]["relative_std"]) for r in refs]
        print(f"{p:<44} {cells[0]:>10} " + " ".join(f"{c:>12}" for c in cells[1:]))
    ratios = report["std_ratios"]
    print("relative stds predicted at the stated noise; geometric mean of designed / "
          "reference: " + ", ".join(
              f"{r} {ratios[r]['geometric_mean']:.3g}" if ratios[r]["geometric_mean"]
              is not None else f"{r} –" for r in refs))
    print(f"wrote {out / 'profile.csv'}, {out / 'report.json'} and {out / 'report.md'}")
    return 0


def _check_names(spec, names: list[tuple[str, str]]) -> None:
    """Every name of `--parameter` and `--target-std` (`(name, flag)`) a free parameter,
    before any work."""
    if not names:
        return
    from ..model import spec_parameters

    free = [n for n, p in spec_parameters(spec).items() if not p.fixed
            and not n.startswith("sensors.") and not n.endswith((".process_noise", ".initial",
                                                                ".initial_std"))]
    for name, flag in names:
        if name not in free:
            raise InputError(f"'{name}' is not a free parameter of the model; free ones are "
                             f"{', '.join(free)}.", file=str(spec.source), field=flag)


def _limits(args):
    from ..design import ChamberLimits

    return ChamberLimits(args.temperature_range, args.ramp_rate, args.power_range, args.start,
                         args.start_power, args.chamber_settling)


def _target(text: str) -> tuple[str, float]:
    """`NAME=STD`: a relative std as a fraction (0.01) or a percentage (1%)."""
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=STD (nodes.pcb.capacitance=1%), got "
                                         f"{text!r}")
    v = value.strip()
    try:
        std = float(v[:-1]) / 100.0 if v.endswith("%") else float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a relative std such as 0.01 or 1%, got "
                                         f"{value!r}") from None
    if not (std > 0 and std < float("inf")):
        raise argparse.ArgumentTypeError(f"the target std must be > 0, got {value!r}")
    return name.strip(), std


def _shortest(args, spec, limits, out) -> int:
    from ..design import write_design
    from ..design._target import shortest_design
    from ._outputs import staged_folder

    if args.parameter:
        raise InputError("--target-std names its own parameters; drop --parameter.",
                         field="--parameter")
    search = shortest_design(spec, args.duration, dict(args.target_std), dt=args.dt,
                             criterion=args.criterion, limits=limits,
                             n_starts=args.starts or 4, temperature_segments=args.knots,
                             power_segments=args.power_steps, noise=args.noise,
                             progress=args.progress)
    with staged_folder(out) as tmp:
        write_design(search.design, tmp, str(args.model), target=search)
    for length, met, stds in search.tried:
        print(f"{length:>10g} s  {'meets' if met else 'misses'} the targets: " + ", ".join(
            f"{n} {_pct(s)}" for n, s in stds.items()))
    d = search.design.schedule.duration_s
    print(f"shortest length meeting the targets: {d:g} s" if search.met else
          f"the targets are not met even at {d:g} s, the longest allowed (--duration); the "
          "profile of that length is written")
    print(f"wrote {out / 'profile.csv'}, {out / 'report.json'} and {out / 'report.md'}")
    return 0


def _discriminate(args, spec, limits, out) -> int:
    from .. import io
    from ..design._discrimination import discriminate
    from ..design._report import write_discrimination
    from ._outputs import staged_folder

    if args.target_std:
        raise InputError("--target-std asks for one model's parameters; --rivals for telling "
                         "models apart: give one of them.", field="--target-std")
    if args.criterion not in (None, "d") or args.parameter:
        raise InputError("--rivals designs to tell models apart; --criterion and --parameter "
                         "are for a design of one model's parameters.", field="--rivals")
    if args.from_investigation:
        from ..design._from_investigation import rivals_from_investigation

        specs = rivals_from_investigation(args.from_investigation)
        spec = specs[0][1]
        args.model = str(Path(args.from_investigation))
    else:
        specs = [(Path(str(args.model)).stem, spec)]
        for r in args.rivals:
            rival = io.load_model(_resolve_model(r))
            name = Path(r).stem
            while name in [n for n, _ in specs]:
                name += "'"
            specs.append((name, rival))
    args.progress("telling apart " + ", ".join(n for n, _ in specs))
    result = discriminate(specs, args.duration, limits=limits, dt=args.dt,
                          n_starts=args.starts or 1, temperature_segments=args.knots,
                          power_segments=args.power_steps, noise=args.noise,
                          progress=args.progress)
    with staged_folder(out) as tmp:
        report = write_discrimination(result, spec, tmp, str(args.model))
    w = max(16, *(len(n) for n, _ in specs)) + 1
    print(f"{'true':<{w}} {'refitted':<{w}} {'profile':<12} {'2 log LR':>12} "
          f"{'P(decisive)':>12}")
    rows = [("designed", report["designed"]["pairs"])] + [
        (n, r["pairs"]) for n, r in report["references"].items()]
    for name, pairs in rows:
        for p in pairs:
            print(f"{p['true']:<{w}} {p['refitted']:<{w}} {name:<12} "
                  f"{p['expected_2log_lr']:>12.4g} {p['p_decisive']:>12.3f}")
    print("expected log-likelihood-ratio statistic of one run at the stated noise, the "
          "refitted model's parameters free; decisive: a likelihood ratio over 100")
    print(f"wrote {out / 'profile.csv'}, {out / 'report.json'} and {out / 'report.md'}")
    return 0


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.3g} %"


def add_design(sub) -> None:
    p = sub.add_parser(
        "design", help="design the chamber profile that best determines a model",
        description="Design a chamber profile (chamber temperature through knots joined by "
        "ramps, heat-input power in equal steps) that maximizes the Fisher information of "
        "the model's free parameters within the chamber's limits: D-optimal by default, or "
        "the variance of named parameters. Writes DIR/profile.csv (the model's input "
        "columns: `simulate --profile` and a chamber controller read it), DIR/report.json "
        "and DIR/report.md with each parameter's predicted std beside those of a PRBS and "
        "of the calibration schedule compressed to the same length. With --rivals, the "
        "profile instead maximizes the expected log-likelihood ratio between the model and "
        "its rivals, each refitted to the others' readings, and the report gives that ratio "
        "and the probability that one run decides.")
    p.add_argument("--model", default=None,
                   help="model TOML file or built-in model name (required unless "
                   "--from-investigation)")
    p.add_argument("--duration", required=True, type=_duration,
                   help="profile length: seconds, or with a unit (4h, 90min)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--dt", type=_positive_float, default=1.0,
                   help="sample period, s (default 1); the duration must be a whole number "
                   "of them")
    p.add_argument("--temperature-range", type=_pair, default=(-40.0, 85.0),
                   metavar="LOW,HIGH", help="chamber temperature limits, °C (default -40,85; a "
                   "negative LOW is written --temperature-range=-40,85)")
    p.add_argument("--ramp-rate", type=_positive_float, default=10.0, metavar="C_PER_MIN",
                   help="fastest chamber change, °C/min (default 10)")
    p.add_argument("--power-range", type=_pair, default=(0.0, 1.0), metavar="LOW,HIGH",
                   help="power limits of every heat input, W (default 0,1)")
    p.add_argument("--chamber-settling", type=float, default=0.0, metavar="S",
                   help="the chamber's own time constant, s: the air follows the programmed "
                   "setpoint through a first-order lag (default 0: the air is the setpoint); "
                   "profile.csv holds the air, the report the setpoints")
    p.add_argument("--start", type=float, default=25.0,
                   help="chamber temperature at the start, °C; the unit starts at rest there "
                   "(default 25)")
    p.add_argument("--start-power", type=float, default=None,
                   help="power over the first sample period, W (default the low power limit)")
    p.add_argument("--criterion", choices=("d", "variance"), default=None,
                   help="d (default): D-optimal, the joint confidence region of all free "
                   "parameters as small as possible; variance: the variances of the "
                   "parameters named by --parameter (the default with --target-std)")
    p.add_argument("--parameter", action="append", default=None, metavar="NAME",
                   help="a free parameter's dotted name (nodes.pcb.capacitance) for "
                   "--criterion variance; repeat for several")
    p.add_argument("--target-std", action="append", type=_target, default=None,
                   metavar="NAME=STD",
                   help="find the shortest profile, up to --duration, whose predicted "
                   "relative std of the named parameter is at most STD (0.01 or 1%%); repeat "
                   "for several")
    p.add_argument("--rivals", nargs="+", default=None, metavar="R.toml",
                   help="rival model files (or built-in names) reading the same sensors: "
                   "design the profile that best tells --model and them apart instead, each "
                   "refitted to the others' readings")
    p.add_argument("--from-investigation", default=None, metavar="DIR",
                   help="a folder `thermojax investigate` wrote: tell apart the candidates of "
                   "the last near-tie it named, each added to that step's model")
    p.add_argument("--noise", type=_positive_float, default=None,
                   help="sensor noise std, °C, for every sensor (default each sensor's "
                   "`noise`, 0.01 °C unset)")
    p.add_argument("--knots", type=_positive_int, default=None,
                   help="chamber ramps between equally spaced temperature knots (default one "
                   "per 10 min)")
    p.add_argument("--power-steps", type=_positive_int, default=None,
                   help="power levels, equal in length (default one per minute)")
    p.add_argument("--starts", type=_positive_int, default=None,
                   help="searches from different schedules; the best is kept (default 4, "
                   "with --rivals 1)")
    _add_force(p, "an existing --out folder")
    _add_quiet(p)
    p.set_defaults(func=cmd_design)
