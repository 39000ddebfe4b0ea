"""Laws outside the function library (`symbolic = true` cases): `investigate` finds them
by its symbolic search over the missing heat (or by refining a law it added: a search
around it), refits them through the dynamics and ends with the truth's form (its
variables and functions) with the truth's constants within three reported stds, within
1.5x the noise with white residuals, no sensor artifact after the law, and the search's
front in its reports."""

from __future__ import annotations

import json
import tomllib

import pytest

from thermojax.cli import main
from thermojax.model._expression import names, parse

from . import generator as g

HORIZON_S = 2400.0
ARTIFACTS = ("sensor_gain", "sensor_offset", "sensor_lag")


def _functions(tree) -> set[str]:
    out = set()
    stack = [tree]
    while stack:
        t = stack.pop()
        if t[0] == "call":
            out.add(t[1])
            stack += list(t[2])
        elif t[0] == "bin":
            stack += [t[2], t[3]]
        elif t[0] == "neg":
            stack.append(t[1])
    return out


def _final_law(steps, place):
    """`(i, added)`: the last step that added or refined a law at `place` (a refined law
    replaces the one it refines, so it is the model's law there)."""
    return next((i, s["added"]) for i, s in reversed(list(enumerate(steps)))
                if s["added"] and s["added"]["kind"] == "expression"
                and s["added"]["where"] == place)


@pytest.mark.slow
@pytest.mark.parametrize("case", g.symbolic_case_names())
def test_law_outside_the_library_is_found_by_the_search(case, tmp_path):
    files = g.write_case(case, tmp_path / "data", seed=0, horizon_s=HORIZON_S)
    out = tmp_path / "out"
    argv = ["investigate", "--model", str(files["model"]), "--out", str(out),
            "--max-steps", "2", "--search-laws", "1500", "--search-seconds", "600"]
    for p in files["data"]:
        argv += ["--data", str(p)]
    assert main(argv) == 0
    report = json.loads((out / "report.json").read_text())
    info = g.load_case(case)
    expected = info["expected"]
    steps = report["steps"]
    front = steps[0]["symbolic_search"]["front"]
    assert front and all({"complexity", "r2", "expression"} <= set(r) for r in front)
    i, added = _final_law(steps, expected["law"])
    tree = parse(added["expression"])
    assert set(names(tree)) >= set(expected["variables"]), added
    assert set(expected["functions"]) <= _functions(tree), added
    searched = steps[i - 1]["symbolic_search"]
    fronts = searched["front"] + [row for k in ("at_file_values", "refinement")
                                  for row in searched.get(k, {}).get("front", [])]
    assert any(r["expression"] == added["expression"] for r in fronts)  # the search's
    # a refined law replaces the law it refines: the final model holds one law there
    effects = tomllib.loads((out / "model_final.toml").read_text()).get("effects", [])
    assert [e["expression"] for e in effects if e["kind"] == "expression"
            and e["where"] == expected["law"]] == [added["expression"]]
    final = steps[-1]
    label = "-".join(expected["law"])
    for name, truth in expected["parameters"].items():
        p = final["parameters"][f"effects.expression.{label}.{name}"]
        assert abs(p["value"] - truth) < 3 * p["std"], (name, p, truth)
    for c, rmse in final["rmse"].items():
        assert rmse < 1.5 * info["noise"], (c, rmse)
    assert report["stopped_because"] == "residuals_white"
    assert not any(s["added"]["kind"] in ARTIFACTS for s in steps[i:])
    assert "### Laws searched" in (out / "report.md").read_text()
