"""Study: does the missing-physics loop, with no hints, select what Bacher & Madsen did?

Real data: the FlexHouse PRBS1 experiment (`../shared/realdata/prbs1/`, 1,691 samples at
5 min; Bacher & Madsen 2011). From the one-node model `ti.toml`, runs

    thermojax investigate --likelihood kalman --model ti.toml --data prbs1.csv

and prints each step beside the paper's forward selection (Ti → TiTh → TiTeTh → TiTeThTs
→ TiTeThTsAe, one extension at a time, kept when its likelihood-ratio test has p < 5 %).
Every step's addition is tested as the paper tests: `2 Δ log L` against χ² with as many
degrees of freedom as parameters it added. The paper's selected model (`titethtsae.toml`)
is fitted with the same likelihood for its log L and AIC; `reference_logL.txt` holds the
independent optimum (`kf_reference.py`, SciPy). Target (issue 31): at least three effects,
each significant by that test, and an AIC within 10 of the paper's model.

    python experiments/prbs1_forward_selection.py [--out DIR] [--max-steps N]

writes a fresh folder (`DIR` itself, default `results/prbs1_forward_selection-<UTC time>/`) with the investigation (`investigation/`: report, plots, final
model), `selection.md` and `results.json`. About 3-5 minutes on two cores.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _study_cli import ROOT, results_folder, study_parser, write_results  # noqa: E402

DATA = ROOT.parent / "shared" / "realdata" / "prbs1"
PAPER_PATH = [
    ("Ti", "start: one node, interior air"),
    ("TiTh", "a heater with its own mass: extra_node [Ti, Ph]"),
    ("TiTeTh", "an envelope node between interior and outdoors: extra_node [Ti, Ta]"),
    ("TiTeThTs", "a sensor with its own lag: sensor_lag [yTi]"),
    ("TiTeThTsAe", "solar gain on the envelope too: heat_source [Ps, Te]"),
]


def lr_test(prev: dict, step: dict) -> tuple[float, int, float]:
    """`(2 Δ log L, added parameters, p)` of `step` against `prev`, χ² with df = added."""
    lr = 2.0 * (prev["nll"] - step["nll"])
    df = max(int(step["n_params"] - prev["n_params"]), 1)
    return lr, df, float(stats.chi2.sf(lr, df))


def paper_model_fit() -> dict:
    """log L, parameters and AIC of the paper's selected model, fitted here (Kalman)."""
    import thermojax as tj

    spec = tj.load_model(DATA / "titethtsae.toml")
    res = tj.fit(spec, [tj.Experiment.from_telemetry(spec, tj.read_telemetry(
        DATA / "prbs1.csv"))], likelihood="kalman")
    return {"log_l": -res.nll, "n_params": res.n_params, "aic": res.aic}


def table(steps: list[dict], paper: dict, reference_log_l: float) -> str:
    lines = ["| step | added | log L | params | AIC | 2 Δ log L | df | p (χ²) |",
             "|---|---|---|---|---|---|---|---|"]
    for i, s in enumerate(steps):
        added = "start (Ti)" if s["added"] is None else \
            f"{s['added']['kind']} {s['added']['where']}"
        test = "" if i == 0 else "| {:.1f} | {} | {:.2g}".format(*s["_test"])
        lines.append(f"| {i} | {added} | {-s['nll']:.2f} | {s['n_params']} | "
                     f"{s['aic']:.2f} {test or '| | |'} |")
    lines += ["", "The paper's forward selection (Bacher & Madsen 2011):", ""]
    lines += [f"{i}. {name}: {what}" for i, (name, what) in enumerate(PAPER_PATH)]
    lines += ["", f"The paper's selected model fitted here: log L {paper['log_l']:.2f}, "
                  f"{paper['n_params']} parameters, AIC {paper['aic']:.2f} (independent "
                  f"optimum log L {reference_log_l:.2f}, kf_reference.py)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = study_parser("prbs1_forward_selection", __doc__,
                          "at most three steps (the paper's first two extensions)")
    parser.add_argument("--max-steps", type=int, default=6)
    args = parser.parse_args(argv)
    if not (DATA / "prbs1.csv").is_file():
        print(f"error: the PRBS1 data are not at {DATA}; this study needs the shared "
              "real-data folder beside the repository.", file=sys.stderr)
        return 2
    from thermojax.cli import main as cli

    folder = results_folder("prbs1_forward_selection", args.out, args.force)
    code = cli(["investigate", "--likelihood", "kalman", "--model", str(DATA / "ti.toml"),
                "--data", str(DATA / "prbs1.csv"), "--out", str(folder / "investigation"),
                "--max-steps", str(3 if args.quick else args.max_steps)])
    if code != 0:
        return code
    report = json.loads((folder / "investigation" / "report.json").read_text())
    steps = report["steps"]
    for prev, s in zip(steps, steps[1:]):
        s["_test"] = lr_test(prev, s)
    paper = paper_model_fit()
    reference = float((DATA / "reference_logL.txt").read_text().split()[0])
    final = steps[-1]
    res = {
        "steps": [{"added": s["added"], "log_l": -s["nll"], "n_params": s["n_params"],
                   "aic": s["aic"], **({"lr": s["_test"][0], "df": s["_test"][1],
                                        "p": s["_test"][2]} if "_test" in s else {})}
                  for s in steps],
        "stopped_because": report["stopped_because"],
        "paper_model": paper, "paper_reference_log_l": reference,
        "effects_added": len(steps) - 1,
        "every_addition_significant": all(s["_test"][2] < 0.05 for s in steps[1:]),
        "aic_minus_paper": final["aic"] - paper["aic"],
        "target_met": (len(steps) - 1 >= 3 and all(s["_test"][2] < 0.05 for s in steps[1:])
                       and final["aic"] - paper["aic"] <= 10.0),
        "wall_time_s": report.get("wall_time_s"),
    }
    text = table(steps, paper, reference) + (
        f"\nFinal model AIC − the paper's: {res['aic_minus_paper']:.2f} "
        f"(target ≤ 10); effects added: {res['effects_added']}; every addition "
        f"significant: {res['every_addition_significant']}; target met: "
        f"{res['target_met']}. Stopped: {report['stopped_because']}.\n")
    write_results(folder, res, text, "selection.md")
    return 0 if math.isfinite(final["aic"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
