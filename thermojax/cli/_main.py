"""The `thermojax` command line (docs/formats.md §5). Edges only: parse, call the library, report.

Every command exits 0 on success and 2 on a user's mistake, with a one-paragraph
message naming the file, line or row, and field; never a traceback for those.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

import numpy as np

from .._errors import InputError
from ._arguments import (_add_force, _add_quiet, _builtin_model_path, _finite_float,
                         _nonnegative_int, _positive_float, _positive_int, _resolve_model)
from ._progress import Progress
from ._checked_runs import fit_dropping, load_runs
from ._checked_runs import plausible as _plausible, read_runs as _read_runs
from ._compensate import add_compensate
from ._design import add_design
from ._export import add_export
from ._playback import add_playback
from ._rate import add_rate
from ._calibrate import add_calibrate
from ._trim import add_trim
from ._montecarlo import add_montecarlo
from ._outputs import (check_output_file, check_output_folder, mark_own, output_session,
                       staged_file, staged_folder)


def _simulate_to_csv(model_path: Path, profile_arg: str, out: Path, noise: bool, seed: int,
                     dt: float, baseline_power: float, write_states: bool):
    """Shared by `simulate` and `demo`: returns (spec, ts, inputs, states, outputs, measured)."""
    from .. import io
    from ..measurements._telemetry import Telemetry

    from ..measurements._profiles import BUILTIN_PROFILES
    from . import _simulate_checks as checks

    if noise:
        checks.check_seed(seed)
    spec = io.load_model(model_path)
    if not spec.sensor_columns and not write_states:
        raise InputError("the model has no sensors, so the file would hold only its inputs; "
                         "add a [[sensors]] table to the model file, or pass --states to write "
                         "every node temperature.", file=str(model_path), field="sensors")
    builtin = profile_arg in BUILTIN_PROFILES
    checks.check_power(baseline_power, spec, not builtin, str(model_path))
    if builtin:
        checks.check_profile_columns(spec, profile_arg, str(model_path))
        checks.check_profile_size(profile_arg, dt, len(spec.input_columns) + 2 * len(
            spec.nodes) + len(spec.sensors) + 2 * len(spec.effects))
    source = io.load_profile(profile_arg, dt=dt)
    if isinstance(source, Telemetry):
        ts = source.ts
        inputs = io.model_inputs(spec, source)
    else:
        ts = source.ts
        inputs = io.profile_inputs(spec, source, baseline_power)
    if len(ts) < 2:
        raise InputError("the profile has fewer than two samples.", field="--profile")
    steps = np.diff(ts)
    if np.ptp(steps) > 0.01 * np.median(steps):
        raise InputError("`simulate` needs uniformly sampled inputs (jitter under 1 %).",
                         file=profile_arg, field="time_s")

    # Through the package's lazy loader, which switches JAX to float64 first: importing
    # the dynamics directly would simulate in float32 outside the test suite.
    from .. import ThermalNetwork  # noqa: F401
    from ..dynamics._as_written import simulate_as_written
    from ..fitting._bias_simulation import simulated_biases

    ts_uniform = ts[0] + np.median(steps) * np.arange(len(ts))
    # The model as written, effects included, by the simulator `fit` uses.
    sim = simulate_as_written(spec, ts_uniform, inputs)
    states, outputs = sim.states, sim.outputs
    _check_finite_simulation(spec, model_path, inputs, ts_uniform, states, outputs,
                             sim.node_names)
    biases = simulated_biases(spec, ts_uniform, sim)  # bias columns, in their units
    measured = outputs.copy()
    if noise:
        rng = np.random.default_rng(seed)
        stds = np.array([s.noise.value if s.noise is not None else 0.01 for s in spec.sensors])
        measured = outputs + rng.standard_normal(outputs.shape) * stds[None, :]
        for b in spec.biases:  # a bias column's noise in its own unit; none written: none
            if b.noise is not None:
                biases[b.column] = biases[b.column] + rng.standard_normal(len(ts)) * b.noise.value
    channels = {c: inputs[:, j] for j, c in enumerate(spec.input_columns)}
    channels.update({c: measured[:, j] for j, c in enumerate(spec.sensor_columns)})
    channels.update(biases)
    if write_states:
        channels.update({f"state_{n}": states[:, i] for i, n in enumerate(sim.node_names)})
    comments = [f"simulated by thermojax from model '{spec.name}' ({model_path}), "
                f"profile '{profile_arg}'" + (f", sensor noise seed {seed}" if noise else "")]
    io.write_telemetry(out, ts, channels, comments=comments)
    return spec, ts, inputs, states, outputs, measured


def _check_finite_simulation(spec, model_path, inputs, ts, states, outputs,
                             node_names=None) -> None:
    """Refuse to write a simulation that went non-finite, naming the input or node and why."""
    if np.isfinite(states).all() and np.isfinite(outputs).all():
        return
    from ..model._network import local_time_constants

    bad_u = ~np.isfinite(inputs)
    if bad_u.any():
        k, j = np.argwhere(bad_u)[0]
        raise InputError(f"the input {spec.input_columns[j]} is {inputs[k, j]} at t = "
                         f"{ts[k]:g} s, so the simulation is not finite; nothing was written. "
                         "Give finite inputs.", field=spec.input_columns[j])
    dt = float(ts[1] - ts[0])
    bad_x = ~np.isfinite(states)
    if bad_x.any():
        k, i = np.argwhere(bad_x)[0]  # the earliest time first
        node = (node_names or spec.node_names)[i]
    else:  # finite states, a non-finite reading: the sensor's own node
        k, j = np.argwhere(~np.isfinite(outputs))[0]
        node = spec.sensors[j].node
    taus = local_time_constants(spec)
    stiff = min(taus, key=taus.get) if taus else None
    if stiff is not None and taus[stiff] < 1e-6 * dt:
        why = (f"its time constant C/ΣG = {taus[stiff]:.3g} s, far below the "
               f"sample period {dt:g} s, so the sampled model overflows; check its capacitance "
               "and conductances (J/K and W/K)")
        node = stiff
    elif np.abs(inputs).max(initial=0.0) > 1e12:
        why = (f"the inputs reach {np.abs(inputs).max():.3g}, far beyond any temperature (°C) "
               "or power (W); check --power and the profile")
    else:
        why = "check the model's capacitances and conductances (J/K and W/K)"
    raise InputError(f"the simulated temperature of node '{node}' is not finite from t = "
                     f"{ts[k]:g} s: {why}. Nothing was written.", file=str(model_path),
                     field=f"nodes.{node}")


def cmd_simulate(args) -> int:
    out = Path(args.out)
    check_output_file(out, args.force)
    with staged_file(out) as tmp:
        spec, ts, *_ = _simulate_to_csv(_resolve_model(args.model), args.profile, tmp,
                                        args.noise, args.seed, args.dt, args.power, args.states)
    print(f"wrote {out}: {len(ts)} samples x {len(spec.sensor_columns)} sensors "
          f"({', '.join(spec.sensor_columns) or 'node temperatures only'})")
    return 0


def cmd_demo(args) -> int:
    from .._plots import plot_simulation, time_constant_groups
    from ..model._network import local_time_constants

    out = Path(args.out)
    check_output_folder(out, args.force, in_place=True)
    mark_own(out)
    model = _builtin_model_path("imu6")
    print("thermojax demo: the six-node tactical-IMU model through a factory calibration "
          "schedule (1, 5 and 10 °C/min ramps between -40 and +85 °C plateaus), 1 s samples, "
          "ASIC dissipating 0.05 W.")
    csv = out / "imu6_calibration.csv"
    spec, ts, inputs, states, outputs, measured = _simulate_to_csv(
        model, "calibration", csv, noise=True, seed=0, dt=1.0, baseline_power=0.05,
        write_states=True)
    names = spec.node_names
    i_pm, i_asic, i_mems = names.index("proof_mass"), names.index("asic"), names.index("mems")
    lag = states[:, i_pm] - states[:, i_asic]
    grad = states[:, i_pm] - states[:, i_mems]
    # A static calibration maps the ASIC reading to the proof mass with a polynomial of
    # that reading; what it cannot absorb is the dynamic part.
    asic = states[:, i_asic]
    dynamic = lag - np.polyval(np.polyfit(asic, lag, 3), asic)
    png = plot_simulation(
        out / "imu6_calibration.png", ts,
        {c: inputs[:, j] for j, c in enumerate(spec.input_columns)},
        {n: states[:, i] for i, n in enumerate(names)},
        {c: measured[:, j] for j, c in enumerate(spec.sensor_columns)},
        reference="asic", title="The six-node IMU through the calibration schedule",
        groups=time_constant_groups(local_time_constants(spec)),
        dynamic={"proof mass − ASIC, after a static cubic in the ASIC temperature": dynamic},
        dynamic_title=f"Proof mass − ASIC is {lag.min():+.2f} .. {lag.max():+.2f} K, mostly a "
        f"static offset; a static calibration leaves this dynamic part")
    print(f"  proof mass minus on-die (ASIC) sensor: {lag.min():+.3f} .. {lag.max():+.3f} K; "
          f"a static cubic in the ASIC temperature absorbs all but {dynamic.min():+.3f} .. "
          f"{dynamic.max():+.3f} K, the dynamic lag only an observer can follow")
    print(f"  proof mass minus MEMS die:             {grad.min():+.4f} .. {grad.max():+.4f} K")
    print(f"wrote {csv}")
    print(f"wrote {png}")
    if args.quick:
        return 0
    from ._demo import run_demo

    print("\nThe missing-physics story: a three-node sensor module (housing, board, die) "
          "in a chamber. The believed model (thermojax/data/chain3.toml) misses two effects; "
          "the data are two chamber ramps with the die dissipating switched power. "
          "`investigate` fits, diagnoses, adds the best supported effect and refits until "
          "nothing systematic is left.")
    report = run_demo(out, progress=args.progress)
    _print_story(report)
    print(f"the report is {out / 'investigation' / 'report.md'} "
          f"(with {out / 'investigation' / 'report.json'} and plots)")
    return 0


def cmd_fit(args) -> int:
    import warnings

    from .. import io
    from ..fitting._fit import fit, profile_interval
    from ..fitting._hold_check import hold_findings
    from ..fitting._implausible_fit import implausible_fit
    from ..fitting._interval_check import check_intervals
    from ..fitting._fit_report import (file_values, comparison_table, format_parameter_table,
                                       parameter_rows, write_fit_outputs)

    out = Path(args.out)
    check_output_folder(out, args.force)
    spec = io.load_model(_resolve_model(args.model))
    _check_profile_names(spec, args.profile or [], args.likelihood)
    outliers = getattr(args, "outliers", "stop")
    experiments, telemetry, dropped = load_runs(spec, args.data, outliers)
    args.progress(f"fitting {len(experiments)} run(s) under the {args.likelihood} likelihood "
                  "(the first evaluation compiles the model)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result, experiments = fit_dropping(spec, experiments, telemetry, dropped, outliers,
                                           args.progress, likelihood=args.likelihood,
                                           n_starts=args.starts, smoothed=True)
        if _worse_than_mean(result) and args.starts < POOR_FIT_STARTS:
            args.progress(f"{_worse_than_mean(result)}: trying {POOR_FIT_STARTS} starts")
            again, refitted = fit_dropping(spec, experiments, telemetry, dropped, outliers,
                                           args.progress, likelihood=args.likelihood,
                                           n_starts=POOR_FIT_STARTS, smoothed=True)
            if again.nll < result.nll:
                result, experiments = again, refitted
        if _worse_than_mean(result):
            warnings.warn(f"{_worse_than_mean(result)} even from {POOR_FIT_STARTS} starts: "
                          "this is no fit of the data. Check the start values (a "
                          "conductance or capacitance off by orders of magnitude), the "
                          "columns' units, and the model's structure.")
        for finding in implausible_fit(spec, result.spec):
            warnings.warn(finding)
        for finding in hold_findings(spec, result.nll, lambda other: fit(
                other, experiments, likelihood=args.likelihood).nll, args.progress):
            warnings.warn(finding)
        profiles = ({} if getattr(args, "no_interval_check", False)
                    else check_intervals(result, args.progress))
        for name in args.profile or []:
            if name in profiles:
                continue
            args.progress(f"profile likelihood of {name}")
            lower, upper = profile_interval(result, name)
            profiles[name] = {"level": 0.95, "lower": lower, "upper": upper}
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    with staged_folder(out) as tmp:
        report = write_fit_outputs(result, experiments, tmp, list(args.data), profiles,
                                   initial=spec, dropped=dropped,
                                   warnings=[str(w.message) for w in caught])
    print(format_parameter_table(parameter_rows(report, file_values(spec))))
    print()
    print(comparison_table(result))
    print(f"wrote {out / 'model.toml'}, {out / 'report.json'}, {out / 'report.md'} and plots")
    return 0


# Starts a fit is given when a sensor's fit ends worse than the sensor's own mean.
POOR_FIT_STARTS = 5


def _worse_than_mean(result) -> str:
    """Words for the sensors whose fit % is negative (the model predicts them worse than
    their own mean: a local optimum, not a fit), or ""."""
    percent = getattr(result, "fit_percent", None) or {}  # a result without the metric: none
    bad = {c: v for c, v in percent.items() if v is not None and v < 0}
    if not bad:
        return ""
    return ("the fit stopped where " + ", ".join(f"{c} (fit {v:.0f} %)" for c, v in
                                                    bad.items())
            + " is predicted worse than by its own mean")


def _check_profile_names(spec, names: list[str], likelihood: str) -> None:
    """`fit --profile NAME`: every NAME a free parameter of the model, before any work."""
    if not names:
        return
    if likelihood != "output_error":
        raise InputError("profile-likelihood intervals are computed for output-error fits "
                         "only; drop --profile or use --likelihood output_error.",
                         field="--profile")
    from ..model import spec_parameters

    free = [n for n, p in spec_parameters(spec).items() if not p.fixed
            and not n.startswith("sensors.") and not n.endswith(".process_noise")]
    for name in names:
        if name not in free:
            raise InputError(f"'{name}' is not a free parameter of the model; free ones are "
                             f"{', '.join(free)}.", file=str(spec.source), field="--profile")


LIKELIHOOD_HELP = (
    "output_error (default): the model is run from its initial state on the measured inputs "
    "alone and compared with every reading; use it when the model is close to complete and "
    "the sensors are quiet, as for a chamber test. kalman: each reading corrects the model's "
    "state before the next is predicted (a Kalman filter with the nodes' process noise); use "
    "it when heat the model does not have (weather, occupants, an unlogged source) moves "
    "the temperatures, as in a building or field log, or when output_error leaves slow "
    "wandering residuals")

_OUTLIERS_HELP = {
    "fit": "drop it (a sensor cell becomes a dropped sample, an input cell is filled from its "
           "neighbours as its hold says); fit then also drops a sensor sample that alone "
           "decided the fit, and refits",
    "diagnose": "drop it (a sensor cell becomes a dropped sample, an input cell is filled "
                "from its neighbours as its hold says) before the model is fitted and the "
                "candidates are ranked",
    "investigate": "drop it (a sensor cell becomes a dropped sample, an input cell is filled "
                   "from its neighbours as its hold says) before the first step",
}


def _add_fit_arguments(p, command: str) -> None:
    """--model, --data (repeatable), --out, --likelihood, --outliers, --force: shared by
    fit, diagnose, investigate (`command` words the --outliers help for each)."""
    p.add_argument("--model", required=True, help="model TOML file or built-in model name")
    p.add_argument("--data", required=True, action="append", help="telemetry CSV (repeatable)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--likelihood", choices=["output_error", "kalman"], default="output_error",
                   help=LIKELIHOOD_HELP)
    p.add_argument("--outliers", choices=["stop", "drop"], default="stop",
                   help="a cell the model's units and the other samples rule out: stop (the "
                   "default, naming each by line and column) or " + _OUTLIERS_HELP[command])
    _add_force(p, "an existing --out folder")
    _add_quiet(p)


def _add_fit(sub):
    p = sub.add_parser("fit", help="fit a model to one or more chamber runs",
                       description="Fit the free parameters of a model to one or more telemetry "
                       "CSV files (one chamber run each; parameters shared, each run with its "
                       "own initial state). Writes DIR/model.toml, DIR/report.json and plots.")
    _add_fit_arguments(p, "fit")
    p.add_argument("--starts", type=_positive_int, default=1,
                   help="number of starts (multi-start, at least 1)")
    p.add_argument("--profile", action="append", metavar="PARAM",
                   help="also compute a 95 %% profile-likelihood interval of this free "
                   "parameter, by its dotted name (repeatable; output error only)")
    p.add_argument("--no-interval-check", action="store_true",
                   help="skip the automatic profile-likelihood check of Wald intervals where "
                   "the curvature is weak or the model has a near-null direction (output "
                   "error; the report says where the two disagree and what trades)")
    p.set_defaults(func=cmd_fit)


def cmd_diagnose(args) -> int:
    from .. import io
    from ..investigation._diagnose import diagnose

    out = Path(args.out)
    check_output_folder(out, args.force)
    spec = io.load_model(_resolve_model(args.model))
    runs = _plausible(spec, _read_runs(args.data), getattr(args, "outliers", "stop"),
                      others=True)
    with staged_folder(out) as tmp:
        report = diagnose(spec, runs, likelihood=args.likelihood, out=tmp,
                          progress=args.progress)
    print(f"{'rank':>4}  {'candidate':<44} {'score test':>11} {'LR':>9} {'p':>9}  supported")
    for i, c in enumerate(report["candidates"][:12]):
        st, lr = c.get("score_test"), c.get("likelihood_ratio")
        print(f"{i + 1:>4}  {_effect_text(c['kind'], c['where']):<44} "
              f"{'–' if st is None else f'{st:.1f}':>11} {'–' if lr is None else f'{lr:.1f}':>9} "
              f"{c['p_value']:>9.2g}  {'yes' if c['supported'] else 'no'}")
        if c.get("tied_with"):
            print(f"{'':6}near-tie: the data could not tell it apart from {_ties_text(c)}")
    print("score test: evidence without refitting; LR: likelihood-ratio statistic "
          "2 (-log L before - after) of a refit")
    if not any(c["supported"] for c in report["candidates"]):
        bad = [col for col, p in (report.get("whiteness_p") or {}).items()
               if p is not None and p <= 0.05]
        if bad:
            print(f"unexplained: the residuals of {', '.join(bad)} are not white and no "
                  "candidate effect is supported")
    if report.get("advice"):
        print(f"advice: {report['advice']}")
    print(f"wrote {Path(args.out) / 'report.json'}, {Path(args.out) / 'report.md'} and plots")
    return 0


def cmd_investigate(args) -> int:
    from .. import io
    from ..investigation._investigate import investigate
    from ..investigation._symbolic_step import SearchSettings

    out = Path(args.out)
    check_output_folder(out, args.force, in_place=True)
    spec = io.load_model(_resolve_model(args.model))
    runs = _plausible(spec, _read_runs(args.data), getattr(args, "outliers", "stop"),
                      others=True)
    mark_own(out)  # finished steps are kept here; a rerun resumes from them
    report = investigate(spec, runs, likelihood=args.likelihood, out=out,
                         max_steps=args.max_steps, resume=not args.restart,
                         progress=args.progress, network=not args.no_network,
                         search=(SearchSettings(args.search_laws, max(args.search_seconds, 0.0) or None)
                                 if args.search_laws else None))
    _print_story(report)
    print(f"wrote {out / 'report.json'}, {out / 'model_final.toml'} and {out / 'report.md'}")
    return 0


def _effect_text(kind, where) -> str:
    return f"{kind} ({'-'.join(str(w) for w in where)})"


def _ties_text(c: dict) -> str:
    ties = c.get("tied_with") or []
    return ", ".join(_effect_text(k, w) for k, w in ties)


def _print_story(report: dict) -> None:
    from ..investigation._evidence import is_added

    steps = report["steps"]
    for i, step in enumerate(steps):
        added = step["added"]
        what = "start" if added is None else f"+ {_effect_text(added['kind'], added['where'])}"
        rmse = ", ".join(f"{c} {v:.4g}" for c, v in step["rmse"].items())
        print(f"  step {i}: {what:<48} RMSE {rmse}")
        if added is not None and i > 0:
            prev = steps[i - 1]
            chosen = next((c for c in prev.get("candidates") or []
                           if is_added(c, added)), None)
            if chosen and chosen.get("tied_with"):
                print(f"          near-tie: the data could not tell it apart from "
                      f"{_ties_text(chosen)}")
                if prev.get("separation"):
                    print(f"          what would separate them: {prev['separation']}")
    print(f"  stopped because: {report['stopped_because']}")
    if report.get("unexplained"):  # only when something is left unexplained
        print(f"  unexplained: {report['unexplained']}")
    if report.get("advice"):
        print(f"  advice: {report['advice']}")


def _add_diagnose(sub):
    p = sub.add_parser("diagnose", help="rank candidate effects for a model",
                       description="Fit a model to one or more runs and rank every candidate "
                       "effect of the vocabulary (docs/formats.md §3) at every place the model allows, "
                       "data columns it does not use included, without changing the model. "
                       "Writes DIR/report.json, DIR/report.md and diagnostic plots.")
    _add_fit_arguments(p, "diagnose")
    p.set_defaults(func=cmd_diagnose)


def _add_investigate(sub):
    p = sub.add_parser("investigate", help="find and add the missing physics, step by step",
                       description="Run the missing-physics loop: fit, diagnose, add the best "
                       "supported effect, refit, repeat until the residuals are white or no "
                       "candidate is supported. Writes DIR/report.json, DIR/model_final.toml, "
                       "DIR/report.md and plots. An interrupted run resumes from its last "
                       "finished step when started again with the same inputs.")
    _add_fit_arguments(p, "investigate")
    p.add_argument("--max-steps", type=_nonnegative_int, default=4,
                   help="most effects to add (default 4)")
    p.add_argument("--restart", action="store_true",
                   help="ignore a checkpoint in DIR and start from the given model")
    p.add_argument("--no-network", action="store_true",
                   help="stop where nothing is supported, without first training a heat "
                   "network at the node missing most heat (about a minute per such step)")
    p.add_argument("--search-laws", type=_nonnegative_int, default=0, metavar="N",
                   help="at every step whose residuals are not white, search expression "
                   "trees for the missing heat at the node missing most, fitting at most N "
                   "laws (1500 is a good start: about a minute a step); its best are "
                   "candidates beside the others. The same budget refines a law the model "
                   "holds (a search around it, whose laws replace it) and, where nothing "
                   "is supported, searches the missing heat at the model file's values "
                   "(default 0: no search, the library's laws only)")
    p.add_argument("--search-seconds", type=float, default=60.0, metavar="S",
                   help="stop that search after S seconds with the laws found so far "
                   "(default 60; 0: no limit but --search-laws)")
    p.set_defaults(func=cmd_investigate)


def cmd_run(args) -> int:
    from ._runner import run_config

    folder = run_config(args.config, progress=args.progress)
    print(f"results in {folder}")
    return 0


def _add_run(sub):
    p = sub.add_parser("run", help="run a config-driven experiment",
                       description="Run an experiment config (configs/experiments/*.toml): "
                       "model, data or synthetic runs, likelihood, options. Each run writes a "
                       "new results folder with the resolved config, package versions and "
                       "outputs; nothing is overwritten.")
    p.add_argument("config", help="experiment config TOML")
    _add_quiet(p)
    p.set_defaults(func=cmd_run)


def _add_simulate(sub):
    p = sub.add_parser("simulate", help="simulate a model through a chamber profile",
                       description="Simulate a model (TOML, or built-in 'imu6'/'rtd2') through a "
                       "chamber profile (a built-in name such as 'calibration', 'ramp5', 'shock', "
                       "'viscoelastic_dwell', 'power_step', 'prbs', or a telemetry CSV holding the "
                       "model's input columns) and write telemetry CSV.")
    p.add_argument("--model", required=True, help="model TOML file or built-in model name")
    p.add_argument("--profile", required=True, help="built-in profile name or input CSV")
    p.add_argument("--out", required=True, help="output telemetry CSV")
    p.add_argument("--noise", action="store_true",
                   help="add white sensor noise with each sensor's `noise` std (0.01 °C if unset)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--dt", type=_positive_float, default=1.0,
                   help="sample period of a built-in profile, s (default 1)")
    p.add_argument("--power", type=_finite_float, default=0.0,
                   help="constant power added to every heat-input column of a built-in "
                   "profile, W (default 0)")
    p.add_argument("--states", action="store_true",
                   help="also write every node temperature as a column state_<node>")
    _add_force(p, "an existing --out file")
    _add_quiet(p)
    p.set_defaults(func=cmd_simulate)


def cmd_resample(args) -> int:
    from .. import io
    from ..measurements._resample import resample

    out = Path(args.out)
    check_output_file(out, args.force)
    telemetry = io.read_telemetry(args.data, uniform=False)
    fill = ()
    if args.model is not None:
        spec = io.load_model(_resolve_model(args.model))
        fill = tuple(spec.input_columns)
    result = resample(telemetry, args.dt, max_gap=args.max_gap, fill=fill)
    summary = result.summary()
    with staged_file(out) as tmp:
        io.write_telemetry(tmp, result.ts, result.channels, comments=[
            f"written by thermojax resample from {args.data}", *summary])
    for line in summary:
        print(line)
    print(f"wrote {out}")
    return 0


def _add_resample(sub):
    p = sub.add_parser("resample", help="put a real logger file on a uniform time grid",
                       description="Regularize a telemetry CSV with gaps, jitter or dropped "
                       "cells onto a uniform grid: each channel interpolated linearly between "
                       "its own samples; cells farther than --max-gap from a sample on either "
                       "side are left empty (a dropped sample, which fitting skips), except the "
                       "model's input columns (with --model), which are interpolated across "
                       "gaps. Says what it did, on screen and as comments in the file.")
    p.add_argument("--data", required=True, help="telemetry CSV to regularize")
    p.add_argument("--out", required=True, help="new telemetry CSV")
    p.add_argument("--dt", type=_positive_float, default=None,
                   help="new sample period, s (default: the file's median step)")
    p.add_argument("--max-gap", type=_positive_float, default=None,
                   help="do not interpolate between samples farther apart than this, s "
                   "(default 3 periods)")
    p.add_argument("--model", default=None,
                   help="model TOML or built-in name: its input columns are filled across gaps")
    _add_force(p, "an existing --out file")
    p.set_defaults(func=cmd_resample)


def _add_demo(sub):
    p = sub.add_parser("demo", help="end-to-end demo on built-in data",
                       description="Run the end-to-end demo on built-in data: the six-node IMU "
                       "through the calibration schedule, then the missing-physics story "
                       "(`investigate` finding the effects a believed model lacks) with its "
                       "report. A few minutes on two cores.")
    p.add_argument("--out", default="thermojax_demo", help="output folder (default thermojax_demo)")
    p.add_argument("--quick", action="store_true",
                   help="only the simulation part (the IMU through the calibration schedule)")
    _add_force(p, "an existing --out folder")
    _add_quiet(p)
    p.set_defaults(func=cmd_demo)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="thermojax",
        description="Differentiable grey-box identification of lumped-parameter thermal networks.",
        epilog="File formats, the effect vocabulary, report keys and every command: docs/ in "
        "the repository (docs/formats.md, docs/cli.md, docs/reports.md).")
    parser.add_argument("--version", action="version", version=f"thermojax {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                help="what to do (each command has its own --help)")
    _add_simulate(sub)
    _add_fit(sub)
    _add_diagnose(sub)
    _add_investigate(sub)
    _add_run(sub)
    _add_resample(sub)
    _add_demo(sub)
    add_export(sub)
    add_compensate(sub)
    add_playback(sub)
    add_rate(sub)
    add_calibrate(sub)
    add_trim(sub)
    add_montecarlo(sub)
    add_design(sub)
    return parser


def _version() -> str:
    from .. import __version__

    return __version__


_STAGED = ("nothing was written: the output is put in place only when complete; run the "
           "command again to start over")
_INTERRUPTED = {
    "simulate": _STAGED, "resample": _STAGED, "fit": _STAGED, "diagnose": _STAGED,
    "export": _STAGED, "calibrate": _STAGED, "compensate": _STAGED, "design": _STAGED,
    "investigate": "the finished steps are kept in the output folder; started again with "
                   "the same model and data it resumes after the last one (--restart starts "
                   "afresh)",
    "montecarlo": "the finished chunks are kept; run the same command again with --resume "
                  "to compute only the rest",
    "run": "the run folder keeps what was written before the interrupt; running the config "
           "again starts a new folder",
    "demo": "the files written so far are kept; run the demo again to start over",
}


def interrupted_message(command: str) -> str:
    """What Ctrl-C left behind for `command`, in one line (printed to stderr, exit 130)."""
    return f"thermojax {command}: interrupted; " + _INTERRUPTED.get(
        command, "nothing more was written") + "."


@contextlib.contextmanager
def _own_warnings():
    """Python warnings raised while a command runs (the library's, or NumPy's and JAX's)
    printed as the tool's own `warning: ...` lines, without the source path and line
    that Python's default display adds."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message).strip()
        print(f"warning: {text}", file=sys.stderr if file is None else file)

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit status (0, 2 for a user's mistake, 130 on Ctrl-C).

    Called with no `argv` (the `thermojax` script), an interrupted run ends the process
    at once after its message: tearing the interpreter down while XLA's compiler
    threads are busy crashed it (a segfault after Ctrl-C).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    args.progress = Progress(args.command, quiet=getattr(args, "quiet", False))
    if hasattr(args, "no_cache") and not args.no_cache and not os.environ.get(
            "THERMOJAX_NO_CACHE"):
        from ..compilation._cache import enable_compilation_cache

        enable_compilation_cache()
    try:
        with args.progress.running(), output_session(args.command), _own_warnings():
            status = args.func(args)
            if args.progress.interrupted:  # swallowed where Python ignores exceptions
                raise KeyboardInterrupt
            return status
    except InputError as err:
        print(f"thermojax {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(interrupted_message(args.command), file=sys.stderr)
        if argv is None:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(130)
        return 130
