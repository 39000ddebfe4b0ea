"""`thermojax export`: the reference-observer artifact (docs/formats.md §5). Edges only."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from .._errors import InputError
from ._outputs import check_output_folder, staged_folder

FORMATS = ("q16.16", "q8.24", "q15")


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
    from ._main import _resolve_model

    out = Path(args.out)
    check_output_folder(out, args.force)
    model = _resolve_model(args.model)
    if not model.is_file():
        raise InputError("no such model file.", file=str(model), field="--model")
    args.progress(f"designing the observer of {model} at {args.rate:g} Hz "
                  f"({args.method} gains for every sensor subset)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with staged_folder(out) as tmp:
            result = export_observer(model, args.rate, tmp, fixed=args.fixed,
                                     method=args.method, sensors=args.sensor,
                                     operating_point=args.operating_point,
                                     c_float=args.c_float, c_layout=args.c_layout)
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
        print(f"fixed point {m['fixed']['format']}: LSB {m['fixed']['lsb_K']:.3g} K around "
              f"{m['fixed']['reference_C']:g} °C")
    for name, size in result.files.items():
        print(f"  {out / name}  ({size} bytes)")
    return 0


def add_export(sub):
    from ._main import _add_force, _add_quiet, _positive_float

    p = sub.add_parser("export", help="export the reference observer (JSON, .npz, C99)",
                       description="Design the observer of a model at a rate and write it as a "
                       "versioned artifact: DIR/observer.json (metadata, schema 1), "
                       "DIR/observer.npz (matrices, a gain for every sensor subset, offsets) "
                       "and C99 source and header (float64 build by default; with --fixed also the "
                       "fixed-point build). With --check DIR, check an existing artifact.")
    p.add_argument("--model", help="model TOML file or built-in model name")
    p.add_argument("--rate", type=_positive_float, help="observer rate, Hz (e.g. 20)")
    p.add_argument("--out", help="output folder")
    p.add_argument("--fixed", choices=FORMATS, default=None,
                   help="also write the fixed-point build in this format")
    p.add_argument("--method", choices=["kalman", "poles"], default="kalman",
                   help="gains: steady-state Kalman (default) or pole placement at 4x the "
                   "open-loop poles")
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
    p.add_argument("--check", metavar="DIR", default=None,
                   help="only check an existing artifact folder (schema and arrays)")
    _add_force(p, "an existing --out folder")
    _add_quiet(p)
    p.set_defaults(func=cmd_export)
