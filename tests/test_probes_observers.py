"""Issue 67, item 5: the gain-scheduled and the trimmed observers hold a bad input and do
not trust an implausible reading, in NumPy and in the generated C (bit for bit), and flag
both; before, one NaN input made every later estimate NaN and a 1e6 °C reading moved the
state to tens of thousands of degrees."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

import thermojax.reference as ref
from thermojax.io import parse_model
from thermojax.observer import scheduled_design
from thermojax.observer._trim import TrimFactor, TrimPlan, trim_design

MODEL = """
name = "module3"
[[nodes]]
name = "die"
capacitance = 0.5
[[nodes]]
name = "board"
capacitance = 5.0
[[nodes]]
name = "case"
capacitance = 50.0
[[links]]
between = ["die", "board"]
conductance = 0.05
[[links]]
between = ["board", "case"]
conductance = 0.5
[[boundaries]]
node = "case"
input = "T_chamber"
conductance = 1.0
[[heat_inputs]]
node = "die"
input = "P_die"
hold = "zoh"
[[sensors]]
node = "board"
column = "T_board"
noise = 0.01
[[sensors]]
node = "case"
column = "T_case"
noise = 0.01
"""
NONLINEAR = MODEL + """
[[effects]]
kind = "conductance_temperature"
where = ["die", "board"]
alpha = -0.005
"""
T = 400
NAN_INPUT, BIG_READING = 150, 200


def clean_log():
    t = np.arange(T)
    u = np.stack([25.0 + 10.0 * np.sin(t / 60.0), 0.2 * (t // 50 % 2)], 1)
    y = np.stack([25.0 + 10.0 * np.sin(t / 60.0 - 0.2), 25.0 + 10.0 * np.sin(t / 60.0 - 0.1)], 1)
    return np.full(3, 25.0), u, y


def bad_and_held():
    """The log with a NaN input and a 1e6 °C reading, and the same log as the observer
    should take it (the input at its last good value, the reading dropped)."""
    x0, u, y = clean_log()
    bad_u, bad_y = u.copy(), y.copy()
    bad_u[NAN_INPUT, 0] = np.nan
    bad_u[NAN_INPUT + 1, 1] = np.inf
    bad_y[BIG_READING, 0] = 1e6
    held_u, held_y = u.copy(), y.copy()
    held_u[NAN_INPUT, 0] = u[NAN_INPUT - 1, 0]
    held_u[NAN_INPUT + 1, 1] = u[NAN_INPUT, 1]
    held_y[BIG_READING, 0] = np.nan
    return x0, bad_u, bad_y, held_u, held_y


@pytest.fixture(scope="module")
def scheduled():
    return scheduled_design(parse_model(NONLINEAR), 0.5, [-40, 0, 40, 80, 120], "T_board")


@pytest.fixture(scope="module")
def trimmed():
    plan = TrimPlan((TrimFactor("k_case", ("boundaries.case-T_chamber.conductance",),
                                (0.8, 1.0, 1.2)),))
    return trim_design(parse_model(MODEL), 0.5, plan)


def test_scheduled_holds_and_flags_bad_samples(scheduled):
    x0, bad_u, bad_y, held_u, held_y = bad_and_held()
    obs = ref.ScheduledObserver(scheduled)
    got, want = obs.run(x0, bad_u, bad_y), obs.run(x0, held_u, held_y)
    assert np.all(np.isfinite(got.states)) and np.abs(got.states).max() < 200
    np.testing.assert_array_equal(got.states, want.states)
    assert got.input_fault[NAN_INPUT] == 1 and got.input_fault[NAN_INPUT + 1] == 2
    assert got.reading_fault[BIG_READING] == 1
    assert got.s[BIG_READING] == got.s[BIG_READING - 1]  # 1e6 does not schedule
    assert np.count_nonzero(got.input_fault) == 2
    assert np.count_nonzero(got.reading_fault) == 1


def test_trimmed_holds_and_flags_bad_samples(trimmed):
    x0, bad_u, bad_y, held_u, held_y = bad_and_held()
    obs = ref.TrimmedObserver(trimmed, [1.1])
    got = obs.run(x0, bad_u, bad_y)
    flags = obs.input_fault.copy(), obs.reading_fault.copy()
    want = obs.run(x0, held_u, held_y)
    assert np.all(np.isfinite(got)) and np.abs(got).max() < 200
    np.testing.assert_array_equal(got, want)
    assert flags[0][NAN_INPUT] == 1 and flags[0][NAN_INPUT + 1] == 2
    assert flags[1][BIG_READING] == 1


def _compile(paths, exe):
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-ffp-contract=off", "-o", str(exe), str(paths["source"]),
                    str(paths["harness"]), "-lm"], check=True, capture_output=True)


def test_scheduled_c_matches_numpy_on_bad_samples(scheduled, tmp_path):
    x0, bad_u, bad_y, _, _ = bad_and_held()
    want = ref.ScheduledObserver(scheduled).run(x0, bad_u, bad_y)
    paths = ref.generate_scheduled_c(scheduled, "tj_scheduled").write(tmp_path)
    _compile(paths, tmp_path / "prog")
    (tmp_path / "in.bin").write_bytes(ref.pack_scheduled(x0, bad_u, bad_y))
    subprocess.run([str(tmp_path / "prog"), str(tmp_path / "in.bin"),
                    str(tmp_path / "out.bin")], check=True)
    got = ref.unpack_scheduled((tmp_path / "out.bin").read_bytes(), 3)
    assert np.array_equal(got.states, want.states) and np.array_equal(got.s, want.s)


def test_trimmed_c_matches_numpy_on_bad_samples(trimmed, tmp_path):
    from thermojax.reference._trimmed_c import pack_trimmed, unpack_trimmed

    x0, bad_u, bad_y, _, _ = bad_and_held()
    want = ref.TrimmedObserver(trimmed, [1.1]).run(x0, bad_u, bad_y)
    paths = ref.generate_trimmed_c(trimmed, "tj_trimmed").write(tmp_path)
    _compile(paths, tmp_path / "prog")
    (tmp_path / "in.bin").write_bytes(pack_trimmed([1.1], x0, bad_u, bad_y))
    subprocess.run([str(tmp_path / "prog"), str(tmp_path / "in.bin"),
                    str(tmp_path / "out.bin")], check=True)
    got = unpack_trimmed((tmp_path / "out.bin").read_bytes(), 3)
    assert np.all(np.isfinite(got))
    assert np.array_equal(got, want)


@pytest.fixture(scope="module")
def adaptive():
    from thermojax.observer import adaptive_design

    return adaptive_design(parse_model(MODEL), ["links.die-board.conductance"], 2.0,
                           drift=2e-4, ceiling=0.5)


def test_adaptive_holds_and_flags_bad_samples(adaptive):
    x0, bad_u, bad_y, held_u, held_y = bad_and_held()
    filt = ref.AdaptiveReference(adaptive)
    got, want = filt.run(x0, bad_u, bad_y), filt.run(x0, held_u, held_y)
    assert np.all(np.isfinite(got.states)) and np.all(np.isfinite(got.conductances))
    np.testing.assert_array_equal(got.states, want.states)
    np.testing.assert_array_equal(got.conductances, want.conductances)
    assert got.input_fault[NAN_INPUT] == 1 and got.input_fault[NAN_INPUT + 1] == 2
    assert got.reading_fault[BIG_READING] == 1


def test_adaptive_c_matches_numpy_on_bad_samples(adaptive, tmp_path):
    x0, bad_u, bad_y, _, _ = bad_and_held()
    want = ref.AdaptiveReference(adaptive).run(x0, bad_u, bad_y)
    src = ref.generate_adaptive_c(adaptive, "tj_adaptive")
    for name, text in (("tj_adaptive.h", src.header), ("tj_adaptive.c", src.source),
                       ("main.c", src.harness)):
        (tmp_path / name).write_text(text)
    _compile({"source": tmp_path / "tj_adaptive.c", "harness": tmp_path / "main.c"},
             tmp_path / "prog")
    (tmp_path / "in.bin").write_bytes(ref.pack_adaptive(x0, bad_u, bad_y))
    subprocess.run([str(tmp_path / "prog"), str(tmp_path / "in.bin"),
                    str(tmp_path / "out.bin")], check=True)
    got = ref.unpack_adaptive((tmp_path / "out.bin").read_bytes(), 3, 1)
    assert np.array_equal(got.states, want.states)
    assert np.array_equal(got.conductances, want.conductances)


def test_multirate_ramps_hold_a_non_finite_bias_in_numpy_and_c(tmp_path):
    """A NaN or inf bias published by the thermal task never enters the inertial ramp
    (before, the ramp started from NaN forever after): the last target is held."""
    from thermojax.reference._multirate import _ramped

    T, q, ratio = 40, 2, 8
    bias = np.stack([np.linspace(0, 1, T), np.linspace(2, 1, T)], 1)
    bias[10, 0], bias[11, 1], bias[12, 0] = np.nan, np.inf, -np.inf
    b0 = np.zeros(q)
    delay = np.arange(T) % ratio
    want = _ramped(bias, b0, ratio, delay, codes=False).inertial
    assert np.all(np.isfinite(want))
    src = ref.generate_multirate_c("tj_multirate", q, ratio)
    for name, text in (("tj_multirate.h", src.header), ("tj_multirate.c", src.source),
                       ("main.c", src.harness)):
        (tmp_path / name).write_text(text)
    _compile({"source": tmp_path / "tj_multirate.c", "harness": tmp_path / "main.c"},
             tmp_path / "prog")
    (tmp_path / "in.bin").write_bytes(ref.pack_multirate(b0, bias, delay))
    subprocess.run([str(tmp_path / "prog"), str(tmp_path / "in.bin"),
                    str(tmp_path / "out.bin")], check=True)
    got = np.frombuffer((tmp_path / "out.bin").read_bytes(), np.float64).reshape(-1, q)
    assert np.array_equal(got, want)
