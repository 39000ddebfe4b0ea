"""A report that never contradicts itself: one whiteness verdict per step, from the
numbers its table shows; the stopping sentence agrees with it; a period is named only
where three cycles fit in the record.

The sequences are generated with a known answer: white noise is white, a random walk is
not, an AR(1) of a chosen small correlation sits between the loop's threshold (0.01)
and the diagnostics' default (0.05)."""

import re

import numpy as np

from thermojax.fitting._residual_analysis import ljung_box
from thermojax.discovery import describe
from thermojax.investigation._investigation_report import write_investigation_report

DT = 60.0
COLUMNS = ["T_room", "T_wall"]
INPUTS = ["T_out", "P_heat"]


def _traces(residuals, n=900):
    """Run traces whose measured minus predicted is `residuals[r]` (n, 2) per run."""
    runs = []
    for r, res in enumerate(residuals):
        ts = np.arange(n) * DT
        t_out = 10.0 + 5.0 * np.sin(2 * np.pi * ts / 86400.0)
        power = np.where((ts // 3600) % 3 == 0, 500.0, 0.0)
        predicted = np.column_stack([20.0 + 0.1 * t_out, 15.0 + 0.2 * t_out])
        runs.append({"name": f"run{r}", "ts": ts, "measured": predicted + res,
                     "predicted": predicted, "inputs": np.column_stack([t_out, power])})
    return runs


def _table(md: str, header_start: str) -> list[list[str]]:
    """The rows of the first Markdown table whose header starts with `header_start`."""
    lines = md.splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[k + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def _p(cell: str) -> float:
    return 0.0 if cell.startswith("<") else float(cell)


def _report(likelihood, whiteness_p, rmse, stopped="residuals_white", white_p=0.01):
    return {"schema": 1, "likelihood": likelihood, "stopped_because": stopped,
            "final_model": "model_final.toml", "white_p": white_p,
            "steps": [{"added": None, "n_params": 6, "rmse": rmse, "nll": 10.0, "aic": 32.0,
                       "bic": 40.0, "whiteness_p": whiteness_p,
                       "whiteness_lags": {c: 20 for c in whiteness_p}, "candidates": []}]}


def test_kalman_stop_names_white_innovations_and_the_free_run_that_is_not():
    """The case seen on a building log: the loop stopped `residuals_white` (innovations
    p 0.065) while the free run drifted by degrees. The table shows both sequences, each
    named and judged at the loop's threshold; the verdict and the stopping sentence say
    the innovations are white and the free run is not, with its RMSE."""
    rng = np.random.default_rng(3)
    innovations = [rng.standard_normal((900, 2)) for _ in range(2)]
    p_innov = {c: ljung_box([x[:, j] for x in innovations])[1] for j, c in enumerate(COLUMNS)}
    assert all(p > 0.01 for p in p_innov.values())  # white noise drawn white
    walks = [np.cumsum(0.3 * rng.standard_normal((900, 2)), 0) for _ in range(2)]
    rmse = {c: float(np.sqrt(np.mean(np.concatenate([w[:, j] for w in walks]) ** 2)))
            for j, c in enumerate(COLUMNS)}
    report = _report("kalman", p_innov, rmse)
    import tempfile
    from pathlib import Path
    with tempfile.TemporaryDirectory() as d:
        md = write_investigation_report(Path(d), report, [_traces(walks)], COLUMNS,
                                        INPUTS).read_text(encoding="utf-8")
    rows = _table(md, "| column | innovations p")
    assert [r[0] for r in rows] == COLUMNS
    for r in rows:
        assert r[2] == ("yes" if _p(r[1]) > 0.01 else "no") == "yes"  # innovations
        assert r[4] == ("yes" if _p(r[3]) > 0.01 else "no") == "no"   # free run: a walk
    assert md.count("**Whiteness verdict:") == 1
    verdict = md[md.index("**Whiteness verdict:"):].splitlines()[0]
    assert verdict.startswith("**Whiteness verdict: white.**")
    assert "innovations" in verdict and "free run" in verdict and "not white" in verdict
    assert f"{rmse['T_room']:.3g} °C" in verdict  # the free-run error, said plainly
    stop = next(line for line in md.splitlines() if line.startswith("Starting")
                or "It stopped because" in line)
    assert "innovations became white" in stop and "free run is not white" in stop
    # nowhere does the report call the residuals white without naming which ones
    assert "residuals became white" not in md
    # nor say the free-run RMSE equals an estimated noise "by construction": under the
    # Kalman likelihood the free run (here a random walk) is not bound to the noise
    assert "by construction" not in md


def test_output_error_verdict_uses_the_loops_threshold():
    """An AR(1) residual with p between 0.01 (the loop's threshold) and 0.05 (the
    diagnostics' default): the loop stopped white, so the table must say white too."""
    rng = np.random.default_rng(21)
    e = rng.standard_normal((2, 900))
    x = e.copy()
    for r in range(2):
        for k in range(1, 900):
            x[r, k] = 0.07 * x[r, k - 1] + e[r, k]
    res = [np.column_stack([0.05 * x[r], 0.05 * rng.standard_normal(900)]) for r in range(2)]
    p = {c: ljung_box([v[:, j] for v in res])[1] for j, c in enumerate(COLUMNS)}
    assert 0.01 < p["T_room"] < 0.05  # the generated case sits between the thresholds
    report = _report("output_error", p, {c: 0.05 for c in COLUMNS})
    import tempfile
    from pathlib import Path
    with tempfile.TemporaryDirectory() as d:
        md = write_investigation_report(Path(d), report, [_traces(res)], COLUMNS,
                                        INPUTS).read_text(encoding="utf-8")
    rows = _table(md, "| column | free-run p")
    assert {r[0]: r[2] for r in rows} == {"T_room": "yes", "T_wall": "yes"}
    assert "**Whiteness verdict: white.**" in md
    assert "free-run residuals became white" in md
    assert "not white" not in md  # no second verdict anywhere (findings, titles)


def test_not_white_step_stops_for_another_reason_and_says_so():
    """A step whose rule sequence fails: verdict "not white" names the failing column;
    the stopping sentence gives the real reason, not whiteness."""
    rng = np.random.default_rng(5)
    walks = [np.cumsum(0.3 * rng.standard_normal((900, 2)), 0) for _ in range(1)]
    p = {c: ljung_box([w[:, j] for w in walks])[1] for j, c in enumerate(COLUMNS)}
    report = _report("output_error", p, {c: 1.0 for c in COLUMNS},
                     stopped="no_supported_candidate")
    import tempfile
    from pathlib import Path
    with tempfile.TemporaryDirectory() as d:
        md = write_investigation_report(Path(d), report, [_traces(walks)], COLUMNS,
                                        INPUTS).read_text(encoding="utf-8")
    assert "**Whiteness verdict: not white.**" in md
    assert "no candidate effect passed" in md
    assert not re.search(r"became white", md)


def test_a_period_is_named_only_when_three_cycles_fit():
    """A cosine of one or two cycles over the record is a slow swing, not a period (the
    seen report named "period 419400 s": the record's length); five cycles are a
    period, named with its value."""
    t = np.arange(0.0, 419400.0, 1800.0)
    record = t.size * 1800.0
    for cycles in (1, 2):
        d = describe([t], [np.cos(2 * np.pi * cycles * t / record)])
        assert "periodic" not in d, (cycles, d)
    d = describe([t], [np.cos(2 * np.pi * 5 * t / record)])
    assert d == f"a periodic component of period {record / 5:.0f} s"
