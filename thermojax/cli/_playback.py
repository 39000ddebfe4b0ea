"""`thermojax playback DIR --data LOG --out CSV [--inject FAULT ...]`: a log played through
an exported observer, with injected sensor faults, and the verdict per fault (bounded?
recovered after how long?). Edges only; the work is `observer._fault_playback`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._errors import InputError
from ._outputs import check_output_file, staged_file


def cmd_playback(args) -> int:
    from .. import io
    from ..measurements._telemetry import check_sensors
    from ..observer._fault_playback import RECOVERED_K, parse_fault, play_faults
    from ..reference import load_observer

    out = Path(args.out)
    check_output_file(out, args.force)
    art = load_observer(args.observer)
    faults = [parse_fault(text, art.output_names) for text in args.inject or ()]
    log = io.read_telemetry(args.data)
    for c in art.input_names:   # present; a bad cell is the observer's to hold (input_fault)
        log.column(c)
    check_sensors(log, art.output_names)
    if abs(log.dt - art.dt) > 1e-6 * art.dt:
        raise InputError(f"the log is sampled every {log.dt:g} s but the observer runs every "
                         f"{art.dt:g} s; resample the log (thermojax resample --dt "
                         f"{art.dt:g}) or export the observer at {1 / log.dt:g} Hz.",
                         file=log.path, field="time_s")
    if args.build == "fixed" and art.metadata["fixed"] is None:
        raise InputError("the observer has no fixed-point build; export it with --fixed, or "
                         "choose --build float64.", file=str(art.folder), field="--build")
    t = log.ts - log.ts[0]
    u = np.stack([log.column(c) for c in art.input_names], 1)
    y = np.stack([log.column(c) for c in art.output_names], 1)
    args.progress(f"playing {len(t)} samples through the {args.build} observer, "
                  f"{len(faults)} fault(s) injected")
    pb = play_faults(art, t, u, y, faults, args.build)
    names = art.output_names
    channels = {}
    for j, c in enumerate(names):
        channels[f"{c}_reading"] = pb.readings[:, j]
        channels[f"{c}_estimate"] = pb.faulted[:, j]
        channels[f"{c}_clean"] = pb.clean[:, j]
    for key in ("in_use", "healthy", "wire_break", "input_fault", "state_ok", "saturations"):
        channels[key] = getattr(pb, key).astype(float)
    with staged_file(out) as tmp:
        io.write_telemetry(tmp, log.ts, channels, comments=[
            f"written by thermojax playback of {args.data} through {args.observer} "
            f"({args.build})", "faults: " + ("; ".join(f.label for f in faults) or "none"),
            "COLUMN_estimate: the observer's estimate of the reading with the faults; "
            "COLUMN_clean: without them; in_use, healthy, wire_break: channel bit masks "
            f"(bit j: {', '.join(names)}); input_fault: inputs held (bit j: "
            f"{', '.join(art.input_names) or 'none'}); state_ok: every state finite and "
            "in range; saturations: fixed-point saturations so far"])
    figure = out.with_suffix(".png")
    _plot(figure, pb, names, faults)
    for v in pb.verdicts:
        rec = (f"recovered {v.recovered_after_s:g} s after it ended (every estimate within "
               f"{RECOVERED_K:g} K of the clean run)" if v.recovered_after_s is not None
               else "NOT recovered by the end of the log")
        print(f"{v.fault.label}: {'bounded' if v.bounded else 'NOT BOUNDED'} (worst "
              f"{v.worst_K:.3g} K from the clean estimate), {rec}")
    if pb.input_fault.any() or not pb.state_ok.all() or pb.saturations[-1]:
        print(f"the log itself: {int(np.count_nonzero(pb.input_fault))} samples with an input "
              f"held, {int(np.count_nonzero(pb.state_ok == 0))} with a state out of range, "
              f"{int(pb.saturations[-1])} fixed-point saturations")
    print(f"wrote {out} and {figure}")
    return 0


def _plot(path: Path, pb, names, faults) -> None:
    """Readings (faulted), estimates with and without faults, fault windows shaded, and
    the channel masks below."""
    from .._plots import new_figure, save_figure

    fig = new_figure(figsize=(12.0, 7.0))
    ax, flags = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    for j, c in enumerate(names):
        ax.plot(pb.t, pb.readings[:, j], lw=0.6, color=f"C{j}", alpha=0.5,
                label=f"{c} reading (faulted)")
        ax.plot(pb.t, pb.faulted[:, j], lw=1.0, color=f"C{j}", label=f"{c} estimate")
        ax.plot(pb.t, pb.clean[:, j], lw=0.8, color="k", ls=":",
                label="estimate without faults" if j == 0 else None)
    for f in faults:
        for a in (ax, flags):
            a.axvspan(f.start_s, max(f.end_s, f.start_s + (pb.t[1] - pb.t[0])),
                      color="C3", alpha=0.12, lw=0)
    ax.set_ylabel("°C")
    ax.legend(fontsize="small", ncol=2)
    ax.set_title("thermojax playback: injected faults (shaded)")
    for j, c in enumerate(names):
        flags.step(pb.t, j + 0.8 * ((pb.in_use >> j) & 1), where="post", lw=0.9,
                   label=f"{c} in use")
    flags.set_yticks(np.arange(len(names)) + 0.4, names)
    flags.set_xlabel("time from the log's start, s")
    flags.set_ylabel("in use")
    save_figure(fig, path)


def add_playback(sub) -> None:
    from ._arguments import _add_force, _add_quiet

    p = sub.add_parser(
        "playback", help="play a log through an exported observer, with injected faults",
        description="Play a log (telemetry CSV at the observer's rate) through the reference "
        "observer of an artifact written by `thermojax export`, once as recorded and once "
        "with injected sensor faults, and say for each fault whether the observer stayed "
        "bounded and how soon it recovered. Writes a CSV (readings, estimates with and "
        "without the faults, channel masks) and a plot beside it. FAULT is "
        "KIND:COLUMN:START[:END[:VALUE]], times in s from the log's start: rail (reading at "
        "the high ADC rail, or VALUE °C), stuck (frozen at its value at START), open (front "
        "end reports open circuit), dropout (missing), wire-break (off by VALUE K, default "
        "10), spike:COLUMN:TIME[:VALUE] (one sample off by VALUE K, default 30).")
    p.add_argument("observer", help="artifact folder written by thermojax export")
    p.add_argument("--data", required=True, help="the log (its input and sensor columns)")
    p.add_argument("--out", required=True, help="CSV to write (its plot: same name, .png)")
    p.add_argument("--inject", action="append", metavar="FAULT",
                   help="a fault to inject (repeatable)")
    p.add_argument("--build", choices=["float64", "float32", "fixed"], default="float64",
                   help="which reference observer plays (default float64; fixed: the "
                   "artifact's --fixed format)")
    _add_force(p, "an existing --out file")
    _add_quiet(p)
    p.set_defaults(func=cmd_playback)
