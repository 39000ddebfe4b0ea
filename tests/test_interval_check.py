"""Wald intervals checked against the profile likelihood (issue 32, item 4). One noisy,
short run of the rtd2h truth leaves the core's capacitance and link weakly determined;
`check_intervals` profiles them, and its ends are checked against a profile computed
independently: a NumPy exact-hold simulator of the same network (matrices written out by
hand) refitted by `scipy.optimize.least_squares` at each pinned value, the ends found by
`scipy.optimize.brentq`."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.optimize
import scipy.stats

import thermojax as tj
from thermojax.fitting import fit
from thermojax.fitting._interval_check import (MOVED_RELATIVE, check_intervals,
                                               interval_lines, intervals_to_check)
from thermojax.measurements._data import Experiment

from helpers import RTD2H_TEXT, np_simulate, np_steady, rtd2h_inputs

NOISE, N, OFFSET = 0.3, 300, 3.0  # °C on both sensors (fixed in the model), samples, core start
TEXT = RTD2H_TEXT.replace("noise = { value = 0.02, fixed = true }",
                          f"noise = {{ value = {NOISE}, fixed = true }}").replace(
    "noise = 0.01", f"noise = {{ value = {NOISE}, fixed = true }}")
HOLDS = ["foh", "zoh"]  # T_fluid, P_heater


def _matrices(cs, cc, gl, gb):
    """rtd2h by hand: states (sheath, core), inputs (T_fluid, P_heater)."""
    A = np.array([[-(gl + gb) / cs, gl / cs], [gl / cc, -gl / cc]])
    B = np.array([[gb / cs, 1.0 / cs], [0.0, 0.0]])
    return A, B


CY = np.array([[0.0, 1.0], [1.0, 0.0]])  # T_core, T_sheath


def _outputs(p, U):
    """Sensor readings for p = (log Cs, log Cc, log Gl, log Gb, core initial °C)."""
    A, B = _matrices(*np.exp(p[:4]))
    x0 = np_steady(A, B, U[0])
    x0[1] = p[4]
    return np_simulate(A, B, CY, x0, U, 1.0, HOLDS)[1]


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(0)
    ts, U = rtd2h_inputs(N, 1.0, rng)
    truth = np.log([0.8, 0.1, 1 / 12, 0.2])
    A, B = _matrices(*np.exp(truth))
    core0 = np_steady(A, B, U[0])[1] + OFFSET
    Y = _outputs(np.r_[truth, core0], U) + NOISE * rng.standard_normal((N, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = fit(tj.parse_model(TEXT, source="weak.toml"), [Experiment(ts, U, Y,
                                                                           name="w.csv")])
    return U, Y, result, check_intervals(result)


def _independent_profile(U, Y, j: int, start):
    """95 % profile interval of parameter j (log units) and the refitted parameters at its
    ends, by SciPy on the hand-written simulator."""
    def residuals(p):
        return ((_outputs(p, U) - Y) / NOISE).ravel()

    best = scipy.optimize.least_squares(residuals, start, x_scale=1.0, xtol=1e-12,
                                        ftol=1e-12)
    chi_min = 2 * best.cost
    free = [k for k in range(5) if k != j]

    def pinned(v):
        def r(q):
            p = best.x.copy()
            p[free] = q
            p[j] = v
            return residuals(p)
        sol = scipy.optimize.least_squares(r, best.x[free], xtol=1e-12, ftol=1e-12)
        p = best.x.copy()
        p[free], p[j] = sol.x, v
        return 2 * sol.cost - chi_min - scipy.stats.chi2.ppf(0.95, 1), p

    ends, at = [], []
    for sign in (-1.0, 1.0):
        far = best.x[j] + sign * 2.0  # a factor e² away: beyond the 95 % end
        e = scipy.optimize.brentq(lambda v: pinned(v)[0], best.x[j], far, xtol=1e-6)
        ends.append(math.exp(e))
        at.append(pinned(e)[1])
    return ends, at, best.x


def test_weak_parameters_are_profiled_and_their_ends_match_an_independent_profile(case):
    U, Y, result, checks = case
    weak = intervals_to_check(result)
    assert set(weak) == {"nodes.core.capacitance", "links.sheath-core.conductance"}
    assert "boundaries.sheath-T_fluid.conductance" not in checks  # 0.6 %: the Wald stands
    start = np.r_[np.log([result.parameters[n]["value"] for n in (
        "nodes.sheath.capacitance", "nodes.core.capacitance", "links.sheath-core.conductance",
        "boundaries.sheath-T_fluid.conductance")]), result.parameters[
        "runs.0.nodes.core.initial"]["value"]]
    for name, j in (("nodes.core.capacitance", 1), ("links.sheath-core.conductance", 2)):
        c = checks[name]
        (lo, hi), at, best = _independent_profile(U, Y, j, start)
        assert c["lower"] == pytest.approx(lo, rel=0.01), name
        assert c["upper"] == pytest.approx(hi, rel=0.01), name
        # the partner the profile names moved with it in the independent profile too
        assert "nodes.core.capacitance" in c["trades_with"] or j == 1
        assert "links.sheath-core.conductance" in c["trades_with"] or j == 2
        other = 3 - j  # core capacitance (1) <-> link conductance (2)
        assert max(abs(p[other] - best[other]) for p in at) > math.log1p(MOVED_RELATIVE)
        # the Wald interval, symmetric in log, misses the profile's skew: said, not hidden
        assert c["agrees"] is False
        assert c["wald_lower"] == pytest.approx(
            result.parameters[name]["value"] * math.exp(
                -scipy.stats.norm.ppf(0.975) * result.parameters[name]["std"]
                / result.parameters[name]["value"]))
    lines = interval_lines(checks)
    assert len(lines) == 2 and all("trade against each other" in ln for ln in lines)


def test_a_well_determined_fit_checks_nothing():
    from helpers import rtd2h_experiments

    result = fit(tj.parse_model(RTD2H_TEXT, source="rtd2h.toml"), rtd2h_experiments(1))
    assert intervals_to_check(result) == {} and check_intervals(result) == {}


def test_fit_reports_the_check_and_can_skip_it(case, tmp_path, capsys):
    import json

    from thermojax.cli import main

    U, Y, _, checks = case
    (tmp_path / "weak.toml").write_text(TEXT)
    tj.write_telemetry(tmp_path / "w.csv", np.arange(N, dtype=float), {
        "T_fluid": U[:, 0], "P_heater": U[:, 1], "T_core": Y[:, 0], "T_sheath": Y[:, 1]})
    for skip in (False, True):
        out = tmp_path / f"out{skip}"
        assert main(["fit", "--model", str(tmp_path / "weak.toml"), "--data",
                     str(tmp_path / "w.csv"), "--out", str(out), "--quiet",
                     *(["--no-interval-check"] if skip else [])]) == 0
        report = json.loads((out / "report.json").read_text())
        md = (out / "report.md").read_text()
        if skip:
            assert "profile_intervals" not in report and "profile check" not in md
            continue
        got = report["profile_intervals"]
        assert set(got) == set(checks)
        for name, c in got.items():
            assert c["lower"] == pytest.approx(checks[name]["lower"], rel=1e-6)
            assert f"profile check of {name}" in md
        assert "| profile |" in md  # the parameter table shows the profile interval


def test_a_run_config_checks_intervals_unless_told_not_to(case, tmp_path, capsys):
    """`thermojax run`: `options.interval_check` (default true) as `fit --no-interval-check`;
    anything but a boolean is refused, naming the field."""
    import json

    from thermojax.cli import main

    U, Y, _, checks = case
    (tmp_path / "weak.toml").write_text(TEXT)
    tj.write_telemetry(tmp_path / "w.csv", np.arange(N, dtype=float), {
        "T_fluid": U[:, 0], "P_heater": U[:, 1], "T_core": Y[:, 0], "T_sheath": Y[:, 1]})
    for option, checked in (("", True), ("interval_check = false", False)):
        (tmp_path / "cfg.toml").write_text('name = "weak"\nmodel = "weak.toml"\nout = "res"\n'
                                           f'data = ["w.csv"]\n\n[options]\n{option}\n')
        capsys.readouterr()
        assert main(["run", str(tmp_path / "cfg.toml"), "--quiet"]) == 0
        folder = capsys.readouterr().out.strip().splitlines()[-1].split("results in ")[1]
        report = json.loads((Path(folder) / "report.json").read_text())
        assert set(report.get("profile_intervals", {})) == (set(checks) if checked else set())
    (tmp_path / "cfg.toml").write_text('name = "weak"\nmodel = "weak.toml"\nout = "res"\n'
                                       'data = ["w.csv"]\n\n[options]\ninterval_check = "no"\n')
    assert main(["run", str(tmp_path / "cfg.toml")]) == 2
    err = capsys.readouterr().err
    assert "cfg.toml" in err and "options.interval_check" in err and "Traceback" not in err


def test_checks_stop_at_their_budget_naming_those_left(case):
    _, _, result, checks = case
    # a budget the first check already spends: it runs, the second is left and named
    with pytest.warns(UserWarning, match="stopped after 1 of 2") as caught:
        partial = check_intervals(result, budget_s=0.0)
    assert list(partial) == list(checks)[:1]
    assert partial[list(checks)[0]]["lower"] == pytest.approx(checks[list(checks)[0]]["lower"])
    assert list(checks)[1] in str(caught[0].message)


def test_a_fit_on_summed_normal_equations_is_not_profiled(case):
    import dataclasses

    from thermojax.fitting._normal_equations import METHOD
    from thermojax.fitting._profile import profile_interval

    _, _, result, _ = case
    long_log = dataclasses.replace(result, method=METHOD)  # as such a fit reports itself
    with pytest.warns(UserWarning, match="not checked against the profile likelihood"):
        assert check_intervals(long_log) == {}
    with pytest.raises(tj.InputError, match="shorter stretch"):
        profile_interval(long_log, "nodes.core.capacitance")
