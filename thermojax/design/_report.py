"""What `design` writes: the profile file a chamber and `simulate` read, and the report
(JSON and Markdown): the criterion, and each parameter's predicted std beside those of the
reference profiles of the same length."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .._json import json_safe
from ..fitting._problem import _is_log
from ._design import Design


def parameter_values(design: Design) -> dict[str, float]:
    """Each judged parameter's value at which the design is linearized (J/K, W/K, s, ...),
    by the names `fit` reports (an effect's parameter by its own name)."""
    prob = design.problem
    out = {}
    for n, t, nui in zip(prob.names, prob.theta, prob.nuisance):
        if nui:
            continue
        v = float(np.exp(t)) if _is_log(n) else float(t)
        target, scale, power = prob.renames.get(n, (n, 1.0, 1.0))
        out[target] = scale * v ** power
    return out


def _positive(design: Design) -> dict[str, bool]:
    """Whether each judged parameter (by its reported name) is a log in the search (its std
    relative)."""
    prob = design.problem
    return {prob.renames.get(n, (n,))[0]: _is_log(n)
            for n, nui in zip(prob.names, prob.nuisance) if not nui}


def std_ratios(design: Design) -> dict[str, dict]:
    """Per reference: the design's std over the reference's per parameter, and their
    geometric mean over the parameters both determine (the D-criterion's own measure)."""
    out = {}
    for name, ref in design.references.items():
        ratios = {}
        for p, s in design.designed.stds.items():
            r = ref.stds.get(p)
            ratios[p] = None if s is None or r is None or r == 0 else s / r
        finite = [v for v in ratios.values() if v is not None and v > 0]
        gm = math.exp(sum(math.log(v) for v in finite) / len(finite)) if finite else None
        out[name] = {"per_parameter": ratios, "geometric_mean": gm}
    return out


def _header(schedule, model: str) -> dict:
    """The keys every `report.json` of `thermojax design` starts with: the command, the
    model, the profile file and the schedule's duration (s), sample period (s) and
    limits."""
    from .. import __version__

    return {"schema": 1, "thermojax_version": __version__, "command": "design",
            "model": model, "profile": "profile.csv", "duration_s": schedule.duration_s,
            "dt_s": schedule.dt, "limits": schedule.limits.to_json()}


def design_report(design: Design, model: str) -> dict:
    """The `report.json` of `thermojax design`."""
    values = parameter_values(design)
    positive = _positive(design)
    judged = list(design.designed.stds)

    def stds(ev):
        return {p: {"relative_std": ev.stds[p],
                    "std": None if ev.stds[p] is None else (
                        ev.stds[p] * abs(values[p]) if positive[p] else ev.stds[p])}
                for p in judged}

    return json_safe({
        **_header(design.schedule, model),
        "criterion": {"kind": design.criterion, "parameters": design.targets,
                      "prior_log_std": 1.0, "value": design.designed.loss},
        "noise": design.noise,
        "schedule": design.schedule.describe(design.params),
        "parameters": {p: {"value": values[p]} for p in judged},
        "designed": {"criterion_value": design.designed.loss, "stds": stds(design.designed),
                     "limits_kept": not design.designed.violations,
                     "undetermined": design.designed.undetermined},
        "references": {name: {"criterion_value": ev.loss, "stds": stds(ev),
                              "limits_kept": not ev.violations, "violations": ev.violations,
                              "undetermined": ev.undetermined}
                       for name, ev in design.references.items()},
        "std_ratios": std_ratios(design),
        "search": {"starts": len(design.start_losses), "criterion_values": design.start_losses,
                   "wall_time_s": design.wall_time_s},
    })


def write_design(design: Design, out: Path, model: str, target=None) -> dict:
    """Write `profile.csv`, `report.json` and `report.md` into the folder `out`; `target`:
    the `TargetSearch` that chose the length, when one did."""
    from ..measurements._inputs import profile_inputs
    from ..measurements._telemetry import write_telemetry

    out = Path(out)
    u = profile_inputs(design.spec, design.profile())
    write_telemetry(out / "profile.csv", design.ts,
                    {c: u[:, j] for j, c in enumerate(design.spec.input_columns)},
                    comments=[f"designed by thermojax design for model '{design.spec.name}' "
                              f"({model}): {'D-optimal' if design.criterion == 'd' else 'least variance'}, "
                              f"{design.schedule.duration_s:g} s at {design.schedule.dt:g} s"])
    report = design_report(design, model)
    if target is not None:
        report["target"] = json_safe({
            "relative_stds": target.targets, "met": target.met,
            "tried": [{"duration_s": d, "met": m, "relative_stds": s}
                      for d, m, s in target.tried]})
    (out / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    (out / "report.md").write_text(markdown(report), encoding="utf-8")
    return report


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.3g} %"


def markdown(report: dict) -> str:
    """`report.md` from `report.json`'s content."""
    lim = report["limits"]
    crit = report["criterion"]
    what = ("D-optimal: the volume of the parameters' joint confidence region, as small as "
            "the limits allow" if crit["kind"] == "d" else
            "the variance of " + ", ".join(crit["parameters"]) + ", as small as the limits allow")
    refs = list(report["references"])
    md = [f"# Experiment design for {report['model']}", "",
          f"A chamber profile of {report['duration_s'] / 3600:.3g} h at {report['dt_s']:g} s "
          f"samples (`{report['profile']}`, the model's input columns), within "
          f"{lim['temperature_c'][0]:g}..{lim['temperature_c'][1]:g} °C, "
          f"{lim['ramp_c_per_min']:g} °C/min and {lim['power_w'][0]:g}..{lim['power_w'][1]:g} W, "
          f"starting at rest at {lim['start_c']:g} °C.", "",
          f"Criterion: {what} (a prior of a factor e on every parameter keeps it finite); "
          f"value {crit['value']:.6g} (lower is better), best of {report['search']['starts']} "
          f"searches in {report['search']['wall_time_s']:.1f} s.",
          "Sensor noise: " + ", ".join(f"{c} {s:g} °C" for c, s in report["noise"].items())
          + ".", "",
          "## Predicted standard errors (relative)", "",
          "| parameter | value | designed | " + " | ".join(refs) + " | "
          + " | ".join(f"designed / {r}" for r in refs) + " |",
          "|---|---:|---:|" + "---:|" * (2 * len(refs))]
    ratios = report["std_ratios"]
    for p, v in report["parameters"].items():
        row = [p, f"{v['value']:.4g}", _pct(report["designed"]["stds"][p]["relative_std"])]
        row += [_pct(report["references"][r]["stds"][p]["relative_std"]) for r in refs]
        row += ["–" if ratios[r]["per_parameter"][p] is None
                else f"{ratios[r]['per_parameter'][p]:.3g}" for r in refs]
        md.append("| " + " | ".join(row) + " |")
    md += ["", "Geometric mean of the std ratios: " + ", ".join(
        f"{r} {'–' if ratios[r]['geometric_mean'] is None else format(ratios[r]['geometric_mean'], '.3g')}"
        for r in refs) + ".", "",
        "References: `prbs`, 60 s bits of power between the power limits at the start "
        "temperature; `calibration`, the packaged calibration schedule compressed in time to "
        "the same length, the power at the middle of its limits."]
    if report["designed"]["undetermined"]:
        md += ["", "Not determined by the designed profile (`–`), as `fit` would report it:", ""]
        md += [f"- {m}" for m in report["designed"]["undetermined"]]
    for r in refs:
        if report["references"][r]["violations"]:
            md.append(f"The `{r}` reference leaves the design's limits ("
                      + "; ".join(report["references"][r]["violations"])
                      + "), which can only favour it.")
    if "target" in report:
        t = report["target"]
        wanted = ", ".join(f"{n} {_pct(v)}" for n, v in t["relative_stds"].items())
        md += ["", "## Shortest length for the target stds", "",
               (f"Targets {wanted}: met at {report['duration_s']:g} s, the shortest length "
                "tried that meets them." if t["met"] else
                f"Targets {wanted}: not met even at {report['duration_s']:g} s, the longest "
                "allowed; the profile of that length is written."), "",
               "| length, s | met | " + " | ".join(t["relative_stds"]) + " |",
               "|---:|---|" + "---:|" * len(t["relative_stds"])]
        for row in t["tried"]:
            md.append(f"| {row['duration_s']:g} | {'yes' if row['met'] else 'no'} | "
                      + " | ".join(_pct(row["relative_stds"][n]) for n in t["relative_stds"])
                      + " |")
    md += ["", "The profile starts at rest; simulate it with `thermojax simulate --model M "
           f"--profile {report['profile']} --noise --out run.csv`, then fit the run to see "
           "the stds achieved."]
    return "\n".join(md) + "\n"


def discrimination_report(disc, model: str) -> dict:
    """The `report.json` of `thermojax design --rivals`."""
    from ._discrimination import DECISIVE

    def pairs(p):
        return [{"true": a, "refitted": b, **v} for (a, b), v in p.items()]

    return json_safe({
        **_header(disc.schedule, model),
        "criterion": {"kind": "discrimination", "hypotheses": disc.names,
                      "decisive_2log_lr": DECISIVE},
        "noise": dict(zip(disc.columns, disc.sigma.tolist())),
        "schedule": disc.schedule.describe(disc.params),
        "designed": {"pairs": pairs(disc.pairs), "limits_kept": not disc.violations},
        "references": {name: {"pairs": pairs(p)} for name, p in disc.references.items()},
        "search": {"wall_time_s": disc.wall_time_s},
    })


def write_discrimination(disc, spec, out: Path, model: str) -> dict:
    """Write `profile.csv`, `report.json` and `report.md` of a discriminating design."""
    from ..measurements._inputs import profile_inputs
    from ..measurements._profiles import Profile
    from ..measurements._telemetry import write_telemetry

    out = Path(out)
    u = profile_inputs(spec, Profile(ts=disc.ts, temperature=disc.temperature, power=disc.power))
    write_telemetry(out / "profile.csv", disc.ts,
                    {c: u[:, j] for j, c in enumerate(spec.input_columns)},
                    comments=[f"designed by thermojax design to tell apart "
                              f"{', '.join(disc.names)}: {disc.schedule.duration_s:g} s at "
                              f"{disc.schedule.dt:g} s"])
    report = discrimination_report(disc, model)
    (out / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    lim = report["limits"]
    md = [f"# A profile that tells {', '.join(f'`{n}`' for n in disc.names)} apart", "",
          f"{report['duration_s'] / 3600:.3g} h at {report['dt_s']:g} s samples "
          f"(`profile.csv`), within {lim['temperature_c'][0]:g}..{lim['temperature_c'][1]:g} °C, "
          f"{lim['ramp_c_per_min']:g} °C/min and {lim['power_w'][0]:g}..{lim['power_w'][1]:g} W.",
          "",
          "For each model taken as true, the other is refitted to its readings (its "
          "parameters and starts), so a difference its parameters can absorb does not count. "
          "`2 log LR` is the expected log-likelihood-ratio statistic of one run at the stated "
          "noise (" + ", ".join(f"{c} {s:g} °C" for c, s in report["noise"].items())
          + f"); a run is decisive when it exceeds {report['criterion']['decisive_2log_lr']:.3g} "
          "(a likelihood ratio of 100), with the probability shown.", "",
          "| true | refitted | profile | expected 2 log LR | P(decisive) |",
          "|---|---|---|---:|---:|"]
    rows = [("designed", report["designed"]["pairs"])] + [
        (name, r["pairs"]) for name, r in report["references"].items()]
    for name, ps in rows:
        for p in ps:
            md.append(f"| {p['true']} | {p['refitted']} | {name} | "
                      f"{p['expected_2log_lr']:.4g} | {p['p_decisive']:.3f} |")
    md += ["", "Run it (`thermojax simulate --profile profile.csv`, or the chamber), then fit "
           "each model to the run: the one with the lower −log L is chosen."]
    (out / "report.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    return report
