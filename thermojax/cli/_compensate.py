"""`thermojax compensate` (docs/formats.md §5): one input reconstructed from a log's
sensor columns, written as `time_s`, `COLUMN`, `COLUMN_std` and `COLUMN_settled`.
Edges only."""

from __future__ import annotations

import sys
from pathlib import Path

from ._outputs import check_output_file, staged_file


def cmd_compensate(args) -> int:
    from .. import io
    from ..measurements._plausibility import check_plausibility
    from ..observer._compensate import compensate
    from ._arguments import _resolve_model

    out = Path(args.out)
    check_output_file(out, args.force)
    figure = out.with_suffix(".png")
    if figure.exists() and not args.force and b"thermojax" not in figure.read_bytes()[:4096]:
        from .._errors import InputError

        raise InputError("the plot beside --out exists and was not written by thermojax; "
                         "choose another --out, or pass --force to replace it.",
                         file=str(figure), field="--out")
    spec = io.load_model(_resolve_model(args.model))
    telemetry = io.read_telemetry(args.data)
    if args.input in spec.input_columns:  # else `compensate` names the inputs to choose from
        check_plausibility(spec, telemetry, unread=(args.input,), can_drop=False)
    args.progress(f"reconstructing {args.input} from {', '.join(spec.sensor_columns)}")
    result = compensate(spec, telemetry, args.input, args.input_noise, say=args.progress)
    how = "chosen by maximum likelihood" if result.chosen else "given"
    c = args.input
    unsettled = _ends(result.settled)
    with staged_file(out) as tmp:
        io.write_telemetry(tmp, result.ts, {
            c: result.estimate, f"{c}_std": result.std,
            f"{c}_settled": result.settled.astype(float)}, comments=[
            f"written by thermojax compensate from {args.data} with {args.model}",
            f"{c} reconstructed from readings on both sides of each sample (the Kalman "
            f"smoother of the observer firmware runs); input noise "
            f"{result.input_noise:.4g} °C/√s ({how})",
            f"{c}_std is the std of {c} at each sample; {c}_settled is 1 where that std is "
            f"within 25 % of the record's interior std ({result.interior_std:.4g}), 0 near "
            "the record's ends, where fewer readings lie on one side",
            *([f"warning: {result.warning}"] if result.warning else [])])
    _plot(figure, telemetry, spec, c, result)
    print(f"{c}: input noise {result.input_noise:.4g} °C/√s ({how}); std "
          f"{result.interior_std:.4g} away from the record's ends"
          + (f", up to {result.std.max():.4g} in the {unsettled} not settled (flagged "
             f"{c}_settled = 0)" if unsettled else "")
          + f"; the causal observer's std {result.filter_std:.4g}; wrote {out} and {figure}")
    if result.warning:
        print(f"warning: {result.warning}", file=sys.stderr)
    return 0


def _ends(settled) -> str:
    """'first 3 and last 12 samples' for the unsettled samples at the ends, or ''."""
    import numpy as np

    bad = ~np.asarray(settled, bool)
    if not bad.any():
        return ""
    first = int(np.argmax(~bad)) if not bad.all() else len(bad)
    last = int(np.argmax(~bad[::-1])) if not bad.all() else 0
    parts = [f"first {first}" if first else "", f"last {last}" if last else ""]
    middle = int(bad.sum()) - first - last
    words = " and ".join(p for p in parts if p) or ""
    text = f"{words} sample(s)" if words else ""
    if middle > 0:
        text = (text + " and " if text else "") + f"{middle} sample(s) inside the record"
    return text


def _plot(path: Path, telemetry, spec, column: str, result) -> None:
    """The sensors, the reconstructed input with its ±2 std band, and the log's own
    column when it has one (a reference), against time."""
    from .._plots import column_unit, new_figure, save_figure

    fig = new_figure()
    ax = fig.add_subplot()
    t = result.ts
    for c in spec.sensor_columns:
        ax.plot(t, telemetry.column(c), lw=0.8, label=f"{c} (sensor)")
    if column in telemetry.names:
        ax.plot(t, telemetry.column(column), lw=0.8, color="k", ls="--",
                label=f"{column} (logged)")
    ax.fill_between(t, result.estimate - 2 * result.std, result.estimate + 2 * result.std,
                    alpha=0.3, color="C3", lw=0)
    ax.plot(t, result.estimate, lw=0.9, color="C3", label=f"{column} reconstructed ±2 std")
    if result.settled is not None and not result.settled.all():
        ax.plot(t[~result.settled], result.estimate[~result.settled], ".", ms=3, color="C1",
                label="not settled (near the record's ends)")
    ax.set_xlabel("time, s")
    ax.set_ylabel(column_unit(column))
    ax.legend()
    ax.set_title(f"thermojax compensate: {column}")
    save_figure(fig, path)  # its metadata names thermojax: a later run may replace it


def add_compensate(sub) -> None:
    from ._arguments import _add_force, _add_quiet, _positive_float

    p = sub.add_parser(
        "compensate", help="reconstruct an input (the fluid a lagging sensor sees) from a log",
        description="Reconstruct one input of the model (the fast temperature a lagging "
        "sensor sees) from the sensor columns of a log, with the model of the observer "
        "firmware runs (the input as a random-walk state, at the log's sample period), "
        "smoothed over the whole log: each sample is estimated from readings on both sides "
        "of it. Writes time_s, COLUMN, COLUMN_std (its std at every sample) and "
        "COLUMN_settled (0 near the record's ends, where fewer readings lie on one side and "
        "the std is more than 25 %% above its interior value). Warns when the std is larger "
        "than the spread of the signal it reconstructs. The input's diffusion (the speed / "
        "noise trade-off) is chosen by maximum likelihood unless --input-noise is given.")
    p.add_argument("--model", required=True, help="model TOML file or built-in model name")
    p.add_argument("--data", required=True, help="the log (telemetry CSV, uniform samples)")
    p.add_argument("--input", required=True, help="the input column to reconstruct")
    p.add_argument("--out", required=True, help="CSV to write")
    p.add_argument("--input-noise", type=_positive_float, default=None,
                   help="the input's diffusion std, °C/√s (default: maximum likelihood)")
    _add_force(p, "an existing --out file")
    _add_quiet(p)
    p.set_defaults(func=cmd_compensate)
