"""Study: how much chamber time does a designed profile save on the six-node IMU?

For the packaged six-node IMU model (1 s samples, 0.01 °C sensors, ASIC power 0..1 W,
chamber −40..85 °C at up to 10 °C/min, starting at rest at 25 °C), designs D-optimal
profiles of 1, 2 and 4 h (`thermojax.design.design`, two starts each) and compares each
parameter's predicted relative std with that of the packaged calibration schedule
compressed to the same length (power at 0.5 W) and of a 60 s power PRBS. It also asks the
chamber-time question directly: is the design of half the length as good as the
reference of the full length (per parameter, and as the geometric mean of the ratios)?

With `--check`, the 1 h design is also run: simulated by `thermojax simulate --noise`,
fitted by `thermojax fit`, and the stds the fit reports set beside the predicted ones.

    python experiments/design_imu6.py [--out DIR] [--quick] [--check]

writes `design.md` (the tables) and `results.json`. `--quick`: 1 and 2 h only.
"""

from __future__ import annotations

import json
import time

import numpy as np

from _study_cli import ROOT, results_folder, study_parser

NAME = "design_imu6"


def geometric_mean(values):
    v = [x for x in values if x is not None and np.isfinite(x) and x > 0]
    return float(np.exp(np.mean(np.log(v)))) if v else None


def main():
    parser = study_parser(NAME, __doc__, "1 and 2 h only")
    parser.add_argument("--check", action="store_true",
                        help="run the 1 h design (simulate with noise, fit) and compare stds")
    args = parser.parse_args()
    out = results_folder(NAME, args.out, args.force)
    from thermojax.design import design
    from thermojax.model import load_model

    spec = load_model(ROOT / "thermojax" / "data" / "imu6.toml")
    hours = (1.0, 2.0) if args.quick else (1.0, 2.0, 4.0)
    runs = {}
    for h in hours:
        t0 = time.perf_counter()
        d = design(spec, h * 3600.0, dt=1.0, n_starts=2, seed=args.seed)
        runs[h] = d
        print(f"{h:g} h: designed in {time.perf_counter() - t0:.0f} s (search "
              f"{d.wall_time_s:.0f} s)", flush=True)
    params = list(runs[hours[0]].designed.stds)
    results = {"hours": list(hours), "parameters": params, "runs": {}}
    md = ["# Designed profiles for the six-node IMU", "",
          "Predicted relative stds (%) at 0.01 °C sensor noise; `–`: not determined by the "
          "profile (the fit's identifiability analysis).", ""]
    for h, d in runs.items():
        rows = {p: {"designed": d.designed.stds[p],
                    **{r: e.stds[p] for r, e in d.references.items()}} for p in params}
        results["runs"][str(h)] = {"stds": rows, "design_time_s": d.wall_time_s,
                                   "criterion": d.designed.loss,
                                   "reference_criteria": {r: e.loss for r, e in
                                                          d.references.items()}}
        md += [f"## {h:g} h", "", "| parameter | designed | calibration | prbs |",
               "|---|---:|---:|---:|"]
        for p in params:
            cells = ["–" if v is None else f"{100 * v:.3g}" for v in
                     (rows[p]["designed"], rows[p]["calibration"], rows[p]["prbs"])]
            md.append(f"| {p} | " + " | ".join(cells) + " |")
        for r in d.references:
            gm = geometric_mean([rows[p]["designed"] / rows[p][r] for p in params
                                 if rows[p]["designed"] is not None and rows[p][r]])
            md.append("")
            md.append(f"Geometric mean of designed / {r}: {gm:.3g}." if gm else "")
        md.append("")
    md += ["## Half the chamber time", "",
           "The design of half the length against the reference of the full length "
           "(ratio of stds; below 1: the short design is better).", "",
           "| design | reference | geometric mean | parameters at or below 1 |", "|---|---|---:|---:|"]
    half = {}
    for h in hours:
        if h / 2 not in runs:
            continue
        short, full = runs[h / 2], runs[h]
        for r in full.references:
            ratios = {p: (short.designed.stds[p] / full.references[r].stds[p]
                          if short.designed.stds[p] is not None and full.references[r].stds[p]
                          else None) for p in params}
            gm = geometric_mean(ratios.values())
            below = sum(1 for v in ratios.values() if v is not None and v <= 1.0)
            judged = sum(1 for v in ratios.values() if v is not None)
            half[f"{h / 2:g}h_vs_{r}_{h:g}h"] = {"ratios": ratios, "geometric_mean": gm}
            md.append(f"| {h / 2:g} h designed | {r}, {h:g} h | "
                      f"{'–' if gm is None else format(gm, '.3g')} | {below}/{judged} |")
    results["half_time"] = half
    if args.check:
        results["check"] = check_by_running(runs[hours[0]], out)
        md += ["", "## Checked by running the 1 h design", "",
               "| parameter | predicted | fit reports | fit / predicted |", "|---|---:|---:|---:|"]
        for p, v in results["check"].items():
            md.append(f"| {p} | {100 * v['predicted']:.3g} % | {100 * v['achieved']:.3g} % | "
                      f"{v['achieved'] / v['predicted']:.3g} |")
    (out / "design.md").write_text("\n".join(md) + "\n")
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    print(f"wrote {out / 'design.md'} and {out / 'results.json'}")


def check_by_running(d, out):
    """Simulate the design with noise and fit it (the command line, as a user would)."""
    from thermojax.cli import main as cli
    from thermojax.design import write_design

    folder = out / "design_1h"
    folder.mkdir(exist_ok=True)
    write_design(d, folder, "imu6")
    run = out / "run_1h.csv"
    assert cli(["simulate", "--model", "imu6", "--profile", str(folder / "profile.csv"),
                "--noise", "--seed", "1", "--out", str(run), "--force", "--quiet"]) == 0
    assert cli(["fit", "--model", "imu6", "--data", str(run), "--out", str(out / "fit_1h"),
                "--force", "--quiet", "--no-interval-check"]) == 0
    report = json.loads((out / "fit_1h" / "report.json").read_text())
    check = {}
    for p, s in d.designed.stds.items():
        e = report["parameters"].get(p)
        if s is None or e is None or e["std"] is None:
            continue
        check[p] = {"predicted": s, "achieved": e["std"] / e["value"]}
    return check


if __name__ == "__main__":
    main()
