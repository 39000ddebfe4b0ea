"""`thermojax compensate` says how sure it is: a std at every sample, the record's ends
marked where the estimate has fewer readings on one side, and a warning where the std
is larger than the signal reconstructed.

A building log as a user would write it: half-hourly samples of the heating power and
a slow indoor probe, the outdoor temperature to reconstruct. The truth comes from an
independent simulator (`scipy.signal.lsim` of the two-node network written out below,
the outdoor temperature piecewise linear on a 3-minute grid, the heating constant over
each half hour), not from thermojax.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

import thermojax as tj
from thermojax.cli import main

DT = 1800.0
SUB = 10  # the simulator's substeps per sample

HOUSE = """name = "house"

[[nodes]]
name = "room"
capacitance = {C_room}

[[nodes]]
name = "probe"
capacitance = {C_probe}

[[links]]
between = ["room", "probe"]
conductance = {G_probe}

[[boundaries]]
node = "room"
input = "T_ext"
conductance = {G_ext}

[[heat_inputs]]
node = "room"
input = "P_heat"
hold = "zoh"

[[sensors]]
column = "T_in"
node = "probe"
noise = {noise}
"""

# a probe lagging the room by 4000 s (over two samples), the room by 5.6 h
DETERMINED = dict(C_room=4e6, G_ext=200.0, C_probe=4e4, G_probe=10.0, noise=0.05)
# a room of 5.8 days behind a 5.6 h probe, read to 0.3 °C: the day's swing outdoors
# moves the reading by about 0.1 °C, under the noise
UNDETERMINED = dict(C_room=3e7, G_ext=60.0, C_probe=2e5, G_probe=10.0, noise=0.3)


def _house_log(tmp_path, n=480, seed=1, **p):
    """Ten days: the outdoor temperature a daily swing between 5 and 20 °C plus a slow
    drift, the heating 0 or 3 kW at random each half hour; the probe's reading with
    white noise. Writes `house.toml` and `house.csv` (no thermojax header)."""
    rng = np.random.default_rng(seed)
    A = np.array([[-(p["G_ext"] + p["G_probe"]) / p["C_room"], p["G_probe"] / p["C_room"]],
                  [p["G_probe"] / p["C_probe"], -p["G_probe"] / p["C_probe"]]])
    B = np.array([[p["G_ext"] / p["C_room"], 1.0 / p["C_room"]], [0.0, 0.0]])
    C = np.array([[0.0, 1.0]])
    t_fine = np.arange(n * SUB + 1) * (DT / SUB)
    drift = np.cumsum(rng.standard_normal(t_fine.size)) * 0.03
    drift -= np.linspace(drift[0], drift[-1], drift.size)
    outdoor = 12.5 + 7.5 * np.sin(2 * np.pi * t_fine / 86400.0 - 1.0) + drift
    heat = np.where(rng.random(n) < 0.5, 0.0, 3000.0)
    x = np.linalg.solve(A, -B @ np.array([outdoor[0], heat[0]]))
    probe = [x[1]]
    for k in range(n):
        seg = slice(k * SUB, (k + 1) * SUB + 1)
        u = np.stack([outdoor[seg], np.full(SUB + 1, heat[k])], 1)
        _, _, xs = scipy.signal.lsim((A, B, C, np.zeros((1, 2))), u,
                                     t_fine[seg] - t_fine[seg][0], X0=x, interp=True)
        x = xs[-1]
        probe.append(x[1])
    ts = DT * np.arange(n + 1)
    reading = np.asarray(probe) + p["noise"] * rng.standard_normal(n + 1)
    power = np.r_[heat, heat[-1]]
    model = tmp_path / "house.toml"
    model.write_text(HOUSE.format(**p))
    log = tmp_path / "house.csv"
    log.write_text("time_s,P_heat,T_in\n" + "".join(
        f"{t:.0f},{w:.0f},{y:.4f}\n" for t, w, y in zip(ts, power, reading)))
    return model, log, ts, outdoor[::SUB], reading


def _compensate(capsys, model, log, out):
    code = main(["compensate", "--model", str(model), "--data", str(log), "--input", "T_ext",
                 "--out", str(out), "--quiet"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    got = tj.read_telemetry(out)
    return got, printed


def test_the_estimate_is_within_its_std_and_its_ends_are_marked(tmp_path, capsys):
    model, log, ts, truth, reading = _house_log(tmp_path, **DETERMINED)
    got, printed = _compensate(capsys, model, log, tmp_path / "outdoor.csv")
    assert list(got.names) == ["T_ext", "T_ext_std", "T_ext_settled"]
    np.testing.assert_array_equal(got.ts, ts)
    est, std = np.asarray(got.column("T_ext")), np.asarray(got.column("T_ext_std"))
    settled = np.asarray(got.column("T_ext_settled"))
    assert np.isfinite(std).all() and (std > 0).all()  # a std at every sample
    assert set(np.unique(settled)) <= {0.0, 1.0}
    # the estimate against the generated truth, within its own std at every sample,
    # the record's ends included
    z = (est - truth) / std
    assert np.mean(np.abs(z) <= 2) >= 0.9, np.abs(z).max()
    assert np.abs(z).max() <= 4, np.abs(z).max()
    # far better than reading the probe as the outdoor temperature
    rmse = np.sqrt(np.mean((est - truth) ** 2))
    assert rmse < np.sqrt(np.mean((reading - truth) ** 2)) / 3, rmse
    # the unsettled samples are the record's ends only, the last one among them, and
    # their std says how much less is known there
    bad = np.flatnonzero(settled == 0)
    assert settled[-1] == 0 and 0 < bad.size < 20
    inner = np.median(std[settled == 1])
    assert np.all((bad < 10) | (bad > ts.size - 11)), bad
    assert np.all(std[settled == 1] <= 1.25 * inner + 1e-9)
    assert std[-1] > 1.25 * inner
    # no unexplained jump at the end: the last samples move by no more than their stds
    step = np.abs(np.diff(est[-6:]))
    assert np.all(step <= 3 * np.hypot(std[-6:-1], std[-5:])), (step, std[-6:])
    assert abs(est[-1] - truth[-1]) <= 3 * std[-1]
    # a log that determines its input draws no warning
    assert "warning" not in printed.err, printed.err
    assert "not settled" in printed.out and "T_ext_settled = 0" in printed.out


def test_a_std_larger_than_the_signal_is_said(tmp_path, capsys):
    model, log, ts, truth, _ = _house_log(tmp_path, **UNDETERMINED)
    out = tmp_path / "outdoor.csv"
    got, printed = _compensate(capsys, model, log, out)
    est, std = np.asarray(got.column("T_ext")), np.asarray(got.column("T_ext_std"))
    assert np.isfinite(std).all() and (std > 0).all()
    # the estimate's std is larger than the spread of what it reconstructs ...
    assert np.median(std) > np.std(est)
    # ... and the warning is warranted: the day's swing outdoors is not recovered
    assert np.corrcoef(est, truth)[0, 1] < 0.5
    assert np.sqrt(np.mean((est - truth) ** 2)) > 0.5 * np.std(truth)
    lines = [line for line in printed.err.splitlines() if line.startswith("warning: ")]
    assert len(lines) == 1, printed.err
    assert "T_ext is not determined by this log" in lines[0]
    assert "larger than the spread of the signal" in lines[0]
    # said as the tool's own message, never Python's (no source path, no class name)
    assert ".py" not in printed.err and "UserWarning" not in printed.err
    # and kept with the file
    assert "not determined by this log" in out.read_text().split("\n0,")[0]


@pytest.mark.parametrize("case", ["determined", "undetermined"])
def test_the_warning_rule_itself(case):
    """The rule on its own: a typical std above the estimate's spread over time warns."""
    from thermojax.observer._compensate import _warning

    t = np.linspace(0.0, 10.0, 200)
    estimate = 12.0 + 5.0 * np.sin(t)  # a spread (std over time) of about 3.5
    std = np.full(t.size, 1.0 if case == "determined" else 7.9)
    settled = np.ones(t.size, bool)
    said = _warning("T_ext", estimate, std, settled, float(std[0]))
    assert (said is None) == (case == "determined")
