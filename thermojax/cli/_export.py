"""`thermojax export`: the reference-observer artifact (docs/formats.md §5). Edges only."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from .._errors import InputError
from ..reference._formats import FORMATS as _FIXED_FORMATS
from ._outputs import check_output_folder, staged_folder

FORMATS = tuple(_FIXED_FORMATS)  # `--fixed` offers every built-in format, in its order


def _count(text: str) -> int:
    import argparse

    from ..reference._faults import COUNTER_MAX

    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of samples, got {text!r}")
    if not 1 <= v <= COUNTER_MAX:
        raise argparse.ArgumentTypeError(f"expected 1..{COUNTER_MAX} samples, got {v}")
    return v


def cmd_export(args) -> int:
    from ..reference import load_observer

    if args.check is not None:
        art = load_observer(args.check)
        m = art.metadata
        print(f"{args.check}: schema {m['schema']}, thermojax {m['thermojax_version']}, model "
              f"'{m['model']}' at {m['rate_hz']:g} Hz; {len(art.state_names)} states, "
              f"inputs {', '.join(art.input_names)}, sensors {', '.join(art.output_names)}"
              + (f"; fixed {m['fixed']['format']}" if m["fixed"] else "") + ": OK")
        if m["fixed"]:
            art.fixed_observer()
        return 0
    missing = [flag for flag, v in (("--model", args.model), ("--rate", args.rate),
                                    ("--out", args.out)) if v is None]
    if missing:
        raise InputError(f"{', '.join(missing)} required (or --check DIR to check an "
                         "existing artifact).", field=missing[0])
    from ..observer._export import export_observer
    from ._arguments import _resolve_model

    out = Path(args.out)
    check_output_folder(out, args.force)
    model = _resolve_model(args.model)
    if not model.is_file():
        raise InputError("no such model file.", file=str(model), field="--model")
    args.progress(f"designing the observer of {model} at {float(args.rate):g} Hz "
                  f"({args.method} gains for every sensor subset)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with staged_folder(out) as tmp:
            result = export_observer(model, args.rate, tmp, fixed=args.fixed,
                                     method=args.method, sensors=args.sensor,
                                     faults=fault_config(args),
                                     reconstruct=args.reconstruct,
                                     input_noise=args.input_noise,
                                     inertial_rate_hz=args.inertial_rate,
                                     adaptive=adaptive_config(args),
                                     schedule=schedule_config(args),
                                     trim=trim_config(args),
                                     operating_point=args.operating_point,
                                     c_float=args.c_float, c_layout=args.c_layout,
                                     speedup=args.speedup,
                                     power_scale=args.power_scale)
            load_observer(tmp)  # what was written reads back
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    m = result.metadata
    worst = max(s["spectral_radius"] for s in m["subsets"])
    print(f"observer of '{m['model']}' at {m['rate_hz']:g} Hz (dt {m['dt_s']:g} s): "
          f"{len(m['states'])} states, {len(m['inputs'])} inputs, sensors "
          f"{', '.join(o['name'] for o in m['outputs'])}; {len(m['subsets'])} sensor subsets, "
          f"slowest error pole |z| = {worst:.6f}")
    print(f"float C build: {m['c_build']['float']}, {m['c_build']['layout']} layout")
    if m["fixed"]:
        eb = m["fixed"]["error_bound"]
        print(f"fixed point {m['fixed']['format']}: LSB {m['fixed']['lsb_K']:.3g} K around "
              f"{m['fixed']['reference_C']:g} °C; guaranteed within {eb['max_K']:.3g} K of "
              f"the exact float64 observer ({eb['assumes']})")
    print(supervision_line(m["faults"]))
    if m["reconstruct"] is not None:
        rc = m["reconstruct"]
        print(f"reconstructs {rc['input']} as state {rc['state_index']} (input noise "
              f"{rc['input_noise_C_per_sqrt_s']:g} °C/√s)")
    if m["multirate"] is not None:
        mr = m["multirate"]
        print(f"multi-rate: {', '.join(mr['bias_channels'])} interpolated at "
              f"{mr['inertial_rate_hz']:g} Hz ({mr['ratio']} ticks per observer step)"
              + (f"; fixed build: {mr['fixed']['prefix']}.c on int32 codes"
                 if mr.get("fixed") else ""))
    if m["schedule"] is not None:
        sc = m["schedule"]
        print(f"gain schedule: {len(sc['points_C'])} points from {sc['points_C'][0]:g} to "
              f"{sc['points_C'][-1]:g} °C, by {sc['by']} ({sc['prefix']}.c)")
    if m["trim"] is not None:
        tr = m["trim"]
        print(f"end-of-line trim: {', '.join(f['name'] for f in tr['factors'])} on a grid of "
              f"{'×'.join(str(len(f['grid'])) for f in tr['factors'])} designs "
              f"({tr['prefix']}.c)" + (
                  "; this unit's factors " + ", ".join(f"{v:.6g}" for v in tr["unit"]["factors"])
                  + f" in {tr['unit']['file']} (interpolation error in Phi "
                  f"{tr['unit']['interpolation_error']['Phi']:.2g}, in L "
                  f"{tr['unit']['interpolation_error']['L']:.2g})" if tr["unit"] else ""))
    if m["adaptive"] is not None:
        ad = m["adaptive"]
        print(f"adaptive filter: tracks {', '.join(ad['tracked'])} "
              f"({ad['design']['substeps']} Tustin substeps a step; {ad['prefix']}.c)")
    for name, size in result.files.items():
        print(f"  {out / name}  ({size} bytes)")
    return 0


def trim_config(args) -> dict | None:
    """The `trim` argument of `export_observer` from `--trim` and `--trim-factors` (the
    factors read from a `thermojax trim` result, matched to the trim file by name)."""
    import json

    if args.trim is None:
        if args.trim_factors is not None:
            raise InputError("--trim-factors without --trim TRIM.toml.", field="--trim-factors")
        return None
    if args.trim_factors is None:
        return {"file": args.trim, "factors": None}
    path = Path(args.trim_factors)
    try:
        record = json.loads(path.read_text())
        found = {f["name"]: float(f["value"]) for f in record["factors"]}
    except FileNotFoundError:
        raise InputError("no such file.", file=str(path), field="--trim-factors") from None
    except (ValueError, KeyError, TypeError) as err:
        raise InputError(f"not a trim result (thermojax trim's trim.json): {err}.",
                         file=str(path), field="--trim-factors") from None
    if record.get("converged") is False:
        raise InputError("these factors did not converge or are undetermined by the unit's "
                         "log (thermojax trim said not to use them): test the unit again.",
                         file=str(path), field="--trim-factors")
    return {"file": args.trim, "factors": found, "factors_file": str(path)}


def schedule_config(args) -> dict | None:
    """The `schedule` argument of `export_observer` from `--schedule` and `--schedule-by`."""
    import numpy as np

    if args.schedule is None:
        if args.schedule_by is not None:
            raise InputError("--schedule-by without --schedule LOW HIGH N.",
                             field="--schedule-by")
        return None
    low, high, count = args.schedule
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise InputError(f"--schedule needs LOW < HIGH, got {low:g} {high:g}.",
                         field="--schedule")
    if count != int(count) or not 2 <= count <= 64:
        raise InputError(f"--schedule N must be a whole number from 2 to 64, got {count:g}.",
                         field="--schedule")
    if args.schedule_by is None:
        raise InputError("--schedule needs --schedule-by COLUMN: the sensor whose reading "
                         "schedules.", field="--schedule-by")
    return {"points": np.linspace(low, high, int(count)).tolist(), "by": args.schedule_by}


def adaptive_config(args) -> dict | None:
    """The `adaptive` argument of `export_observer` from the `--adaptive*` flags."""
    if not args.adaptive:
        if args.adaptive_drift is not None:
            raise InputError("--adaptive-drift without --adaptive: name the conductances to "
                             "track.", field="--adaptive-drift")
        return None
    if args.adaptive_drift is None:
        raise InputError("--adaptive needs --adaptive-drift RATE (per √s): how fast the "
                         "tracked conductances may age.", field="--adaptive-drift")
    return {"tracked": list(args.adaptive), "drift": args.adaptive_drift,
            "ceiling": args.adaptive_ceiling}


def fault_config(args):
    """The `FaultConfig` of the supervision flags (docs/cli.md, "export")."""
    from ..reference import FaultConfig

    if args.limits is not None and not args.limits[0] < args.limits[1]:
        raise InputError(f"the plausible range needs LOW < HIGH, got {args.limits[0]:g} "
                         f"{args.limits[1]:g}.", field="--limits")
    limits = tuple(args.limits) if args.limits is not None else (-55.0, 125.0)
    if args.gate and args.wire_break_threshold is None:
        raise InputError("--gate leaves out samples whose residual exceeds the wire-break "
                         "threshold: give --wire-break-threshold K too.", field="--gate")
    if args.rails is not None:
        lo, hi = args.rails
        if not lo < hi:
            raise InputError(f"the ADC rails need LOW < HIGH, got {lo:g} {hi:g}.",
                             field="--rails")
        if hi <= limits[0] or lo >= limits[1]:
            raise InputError(f"the rails {lo:g}…{hi:g} °C lie outside the plausible range "
                             f"{limits[0]:g}…{limits[1]:g} °C, so every reading would be "
                             "dropped or railed; check the units of --rails and --limits.",
                             field="--rails")
    return FaultConfig(limits=limits, rails=args.rails,
                       residual_threshold=args.wire_break_threshold,
                       wire_break_after=args.wire_break_after,
                       recover_after=args.recover_after, gate=args.gate)


def supervision_line(faults: dict) -> str:
    """One line saying what the exported channel supervision does (observer.json faults)."""
    lo, hi = faults["limits_C"]
    rails = {tuple(r) for r in faults["rails_C"]}
    thr = {t for t in faults["residual_threshold_K"]}
    words = [f"readings outside {lo:g}…{hi:g} °C drop their channel"]
    if rails != {(None, None)}:
        words.append("readings at the ADC rails " + ", ".join(
            f"{'-' if a is None else f'{a:g}'}…{'-' if b is None else f'{b:g}'} °C"
            for a, b in sorted(rails, key=str)) + " get no correction")
    if thr != {None}:
        words.append(f"|residual| > {', '.join(f'{t:g}' for t in sorted(thr, key=str))} K for "
                     f"{faults['wire_break_after']} samples raises wire break, "
                     f"{faults['recover_after']} good samples recover"
                     + ("; a sample over it is not used (gated)" if faults.get("gate") else ""))
    else:
        words.append("no wire-break test (--wire-break-threshold)")
    return "supervision: " + "; ".join(words)


def add_export(sub):
    from ._arguments import _add_force, _add_quiet, _positive_float, rate_hz

    p = sub.add_parser("export", help="export the reference observer (JSON, .npz, C99)",
                       usage="thermojax export --model M --rate HZ --out DIR [options]\n"
                       "       thermojax export --check DIR",
                       description="Design the observer of a model at a rate and write it as a "
                       "versioned artifact: DIR/observer.json (metadata, schema 1), "
                       "DIR/observer.npz (matrices, a gain for every sensor subset, offsets) "
                       "and C99 source and header (float64 build by default; with --fixed also the "
                       "fixed-point build). With --check DIR, check an existing artifact.")
    p.add_argument("--model", help="model TOML file or built-in model name (required "
                   "unless --check)")
    p.add_argument("--rate", type=rate_hz, metavar="HZ",
                   help="observer rate, Hz: a number (20, 0.5) or a fraction (1/1800 for one "
                   "sample every 1800 s); required unless --check")
    p.add_argument("--out", help="output folder (required unless --check)")
    p.add_argument("--fixed", choices=FORMATS, default=None,
                   help="also write the fixed-point build in this format")
    p.add_argument("--method", choices=["kalman", "poles"], default="kalman",
                   help="gains: steady-state Kalman (default; q and R from the model, "
                   "recorded in observer.json 'design') or pole placement: "
                   "4x the open-loop poles, modes already faster than 5 sample periods kept, "
                   "faster poles capped at 1/(5 dt) (docs/observer.md §4)")
    p.add_argument("--sensor", action="append", metavar="COLUMN",
                   help="use only this sensor column (repeatable; default all)")
    p.add_argument("--operating-point", type=float, default=25.0, metavar="T_C",
                   help="uniform temperature (°C) at which a model with nonlinear effects "
                   "is linearized (default 25)")
    p.add_argument("--c-float", choices=["float64", "float32"], default="float64",
                   help="the word of the float C build (default float64)")
    p.add_argument("--c-layout", choices=["rows", "columns"], default="rows",
                   help="the float C build's layout: rows (straight-line, any core; default) "
                   "or columns (vectorized sums and supervision for SIMD cores: gcc -O3 "
                   "with AVX2 or NEON)")
    p.add_argument("--reconstruct", metavar="COLUMN", default=None,
                   help="lag compensation: reconstruct this temperature input (the fluid a "
                   "lagging sensor sees) as the observer's last state, as `thermojax "
                   "compensate` does; needs --input-noise")
    p.add_argument("--input-noise", type=_positive_float, default=None, metavar="Q",
                   help="the reconstructed input's random-walk diffusion, °C/√s (`thermojax "
                   "compensate` prints the maximum-likelihood value for a log)")
    p.add_argument("--inertial-rate", type=_positive_float, default=None, metavar="HZ",
                   help="with bias channels: also write the multi-rate split (tj_multirate.c: "
                   "double buffer and interpolation of the bias corrections at this rate, a "
                   "whole multiple of --rate, e.g. 2000; with --fixed also "
                   "tj_multirate_<fmt>.c on the int32 bias codes)")
    p.add_argument("--speedup", type=_positive_float, default=4.0, metavar="FACTOR",
                   help="with --method poles: observer poles FACTOR times the open-loop "
                   "poles (default 4, at least 1; docs/observer.md §4)")
    p.add_argument("--power-scale", type=_positive_float, default=1.0, metavar="W",
                   help="with --fixed: watts per format unit of a power input (default 1: "
                   "a Q16.16 power spans ±32768 W; docs/observer.md §6)")
    sg = p.add_argument_group("gain scheduling (docs/observer.md §12): a nonlinear model's "
                              "observer at several temperatures, interpolated at run time")
    sg.add_argument("--schedule", type=float, nargs=3, metavar=("LOW", "HIGH", "N"),
                    default=None, help="also write tj_scheduled.c, designed at N temperatures "
                    "from LOW to HIGH °C (N >= 2; cover the range of the scheduling sensor "
                    "and the gradients above it)")
    sg.add_argument("--schedule-by", metavar="COLUMN", default=None,
                    help="the sensor column whose reading schedules (required with "
                    "--schedule)")
    tg = p.add_argument_group("end-of-line trim (docs/observer.md §13): the observer over a "
                              "grid of per-unit scale factors, interpolated once at start-up")
    tg.add_argument("--trim", metavar="TRIM.toml", default=None,
                    help="also write tj_trimmed.c, designed at every point of the trim file's "
                    "factor grid")
    tg.add_argument("--trim-factors", metavar="TRIM.json", default=None,
                    help="a unit's factors (thermojax trim's trim.json): also write its factor "
                    "table tj_trimmed_unit.c and the interpolation's error at it")
    a = p.add_argument_group("adaptive filter (docs/observer.md §11): drifting conductances "
                             "tracked online, tj_adaptive.c bit-exact with the NumPy reference")
    a.add_argument("--adaptive", action="append", metavar="CONDUCTANCE",
                   help="track this conductance (repeatable), by its report name, e.g. "
                   "links.pcb-asic.conductance or boundaries.housing-T_chamber.conductance")
    a.add_argument("--adaptive-drift", type=_positive_float, default=None, metavar="RATE",
                   help="relative random-walk intensity of the tracked conductances, per √s "
                   "(the ageing you expect: RATE·√t is the relative change over t seconds)")
    a.add_argument("--adaptive-ceiling", type=_positive_float, default=0.5, metavar="FRACTION",
                   help="largest relative std of a tracked conductance, the unit-to-unit "
                   "spread (default 0.5)")
    g = p.add_argument_group("channel supervision (recorded in observer.json 'faults', "
                             "honoured by the reference and the C)")
    g.add_argument("--limits", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                   help="plausible range of a reading, °C (default -55 125): a reading "
                   "outside drops its channel at once")
    g.add_argument("--rails", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                   help="ADC rails, °C, every sensor (default none): a reading at or beyond "
                   "a rail gets no correction (anti-windup)")
    g.add_argument("--wire-break-threshold", type=_positive_float, default=None, metavar="K",
                   help="|prediction residual| above which a sample counts as bad, K "
                   "(default: no wire-break test)")
    g.add_argument("--wire-break-after", type=_count, default=10, metavar="N",
                   help="consecutive bad samples that raise wire break and drop the channel "
                   "(default 10)")
    g.add_argument("--gate", action="store_true",
                   help="with --wire-break-threshold: leave a sample whose residual exceeds "
                   "it out of the correction (a spike is ignored, a plausible offset is not "
                   "absorbed before the wire-break flag rises)")
    g.add_argument("--recover-after", type=_count, default=20, metavar="M",
                   help="consecutive good samples that bring a dropped channel back "
                   "(default 20)")
    p.add_argument("--check", metavar="DIR", default=None,
                   help="only check an existing artifact folder (schema and arrays)")
    _add_force(p, "an existing --out folder")
    _add_quiet(p)
    p.set_defaults(func=cmd_export)
