"""Gain scheduling (issue 35, item 3) against an independent simulation of the nonlinear
truth: a die on a board in a case, the die–board conductance temperature dependent
(`G0 (1 + α (T̄ − 25))`, α −0.005/K: ×1.33 at −40 °C, ×0.70 at 85 °C), the die
unmeasured and powered, sensors on the board and the case. The truth is SciPy's
`solve_ivp` of the nonlinear ODE, sample by sample (chamber linear, power held)."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
import scipy.integrate

import thermojax.reference as ref
from thermojax.io import parse_model
from thermojax.observer import scheduled_design

MODEL = """
name = "module3nl"
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
[[effects]]
kind = "conductance_temperature"
where = ["die", "board"]
alpha = -0.005
"""
DT, ALPHA, NOISE = 2.0, -0.005, 0.01
CAP = np.array([0.5, 5.0, 50.0])


def truth(seconds, seed=0):
    """Node temperatures (T, 3), inputs (T, 2) and readings (T, 2): the chamber sweeps
    −40 → 85 → −40 °C, the die power switches 0.1/0.4 W every 10 min."""
    t = np.arange(int(seconds / DT)) * DT
    T_ch = 22.5 - 62.5 * np.cos(2 * np.pi * t / seconds)
    P = np.where((t // 600) % 2 == 0, 0.1, 0.4)
    u = np.stack([T_ch, P], axis=1)

    def rhs(s, x, k):
        fr = (s - t[k]) / DT
        tc = T_ch[k] + fr * (T_ch[k + 1] - T_ch[k])
        g = 0.05 * (1 + ALPHA * (0.5 * (x[0] + x[1]) - 25.0))
        q_db = g * (x[1] - x[0])
        return np.array([q_db + P[k], -q_db + 0.5 * (x[2] - x[1]),
                         0.5 * (x[1] - x[2]) + 1.0 * (tc - x[2])]) / CAP

    x = np.empty((t.size, 3))
    x[0] = _steady(T_ch[0], P[0])
    for k in range(t.size - 1):
        sol = scipy.integrate.solve_ivp(rhs, (t[k], t[k + 1]), x[k], args=(k,),
                                        method="DOP853", rtol=1e-10, atol=1e-10)
        x[k + 1] = sol.y[:, -1]
    y = x[:, 1:] + NOISE * np.random.default_rng(seed).standard_normal((t.size, 2))
    return t, u, x, y


def _steady(tc, p):
    """The nonlinear steady state by fixed-point iteration on the die–board conductance."""
    x = np.array([tc + p * (1 / 0.05 + 1 / 0.5 + 1.0), tc + p * 1.5, tc + p])
    for _ in range(100):
        g = 0.05 * (1 + ALPHA * (0.5 * (x[0] + x[1]) - 25.0))
        x = np.array([tc + p * (1 / g + 1 / 0.5 + 1.0), tc + p * 1.5, tc + p])
    return x


@pytest.fixture(scope="module")
def data():
    return truth(4 * 3600.0)


@pytest.fixture(scope="module")
def spec():
    return parse_model(MODEL)


def bias(states):
    """A gyro-like bias of the die: its temperature and its gradient to the board."""
    return 0.03 * (states[:, 0] - 25.0) + 0.8 * (states[:, 0] - states[:, 1])


def test_scheduling_beats_one_linearization_on_a_sweep_across_the_range(spec, data):
    """Over the sweep (board −40…86 °C, die up to 98 °C) the scheduled observer (six
    points, −40…110 °C) estimates the unmeasured die and the bias at least 5× closer than
    the export's single linearization at 25 °C. What it leaves (about 0.5 K at the hot
    end) is the die–board gradient: the conductance follows their mean, up to 12 K above
    the board reading the schedule is indexed by."""
    t, u, x, y = data
    sched = ref.ScheduledObserver(scheduled_design(spec, 1 / DT, [-40, -10, 20, 50, 80, 110],
                                                   "T_board")).run(x[0], u, y)
    one = ref.ScheduledObserver(scheduled_design(spec, 1 / DT, [25.0, 25.0 + 1e-9],
                                                 "T_board")).run(x[0], u, y)
    settled = t > 1800
    err_s = np.abs(sched.states - x)[settled, 0].max()
    err_1 = np.abs(one.states - x)[settled, 0].max()
    assert err_s < 0.6 and err_1 > 5 * err_s, (err_1, err_s)
    b_s = np.abs(bias(sched.states) - bias(x))[settled].max()
    b_1 = np.abs(bias(one.states) - bias(x))[settled].max()
    assert b_1 > 5 * b_s, (b_1, b_s)
    # the measured sensors are right either way: the gain pulls them to the readings
    assert np.abs(sched.states - x)[settled, 1:].max() < 3 * NOISE
    assert y[:, 0].max() > 80 and y[:, 0].min() < -35 and x[:, 0].max() > 95
    # where the die is near the board, scheduling is near exact
    cool = settled & (np.abs(x[:, 0] - x[:, 1]) < 3)
    assert np.abs(sched.states - x)[cool, 0].max() < 0.1


def test_the_scheduled_observer_in_c_is_bit_exact(spec, data, tmp_path):
    t, u, x, y = data
    design = scheduled_design(spec, 1 / DT, [-40, 0, 40, 85], "T_board")
    y = y.copy()
    y[100:110, 0] = np.nan     # the scheduling sensor drops out: s is held
    want = ref.ScheduledObserver(design).run(x[0], u, y)
    assert np.all(want.s[100:110] == want.s[99])
    src = ref.generate_scheduled_c(design, "tj_scheduled")
    paths = src.write(tmp_path)
    (tmp_path / "in.bin").write_bytes(ref.pack_scheduled(x[0], u, y))
    for opt in ("-O2", "-O3"):
        exe = tmp_path / f"prog{opt}"
        subprocess.run(["gcc", "-std=c99", opt, "-Wall", "-Wextra", "-pedantic", "-Werror",
                        "-ffp-contract=off", "-o", str(exe), str(paths["source"]),
                        str(paths["harness"]), "-lm"], check=True, capture_output=True)
        subprocess.run([str(exe), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")],
                       check=True)
        got = ref.unpack_scheduled((tmp_path / "out.bin").read_bytes(), 3)
        assert np.array_equal(got.states, want.states), opt
        assert np.array_equal(got.s, want.s), opt


def test_export_writes_the_schedule_and_its_c_plays_back_bit_exact(spec, data, tmp_path,
                                                                    capsys):
    """`thermojax export --schedule -40 110 6 --schedule-by T_board`: the artifact's
    schedule is `scheduled_design`'s, `load_observer(DIR).scheduled_observer()` rebuilds
    it, the artifact's own C plays back bit-exact; mistakes are named."""
    from thermojax.cli import main

    model = tmp_path / "module3nl.toml"
    model.write_text(MODEL)
    out = tmp_path / "obs"
    assert main(["export", "--model", str(model), "--rate", str(1 / DT), "--out", str(out),
                 "--schedule", "-40", "110", "6", "--schedule-by", "T_board",
                 "--quiet"]) == 0
    assert "gain schedule: 6 points from -40 to 110 °C, by T_board" in \
        capsys.readouterr().out
    art = ref.load_observer(out)
    obs = art.scheduled_observer()
    direct = scheduled_design(spec, 1 / DT, [-40, -10, 20, 50, 80, 110], "T_board")
    for name in ("points", "Phi", "B0", "B1", "L", "C", "D"):
        assert np.array_equal(getattr(obs.d, name), getattr(direct, name)), name
    t, u, x, y = data
    n = 1800
    want = obs.run(x[0], u[:n], y[:n])
    exe = tmp_path / "prog"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-ffp-contract=off", "-o", str(exe), str(out / "tj_scheduled.c"),
                    str(out / "tj_scheduled_main.c"), "-lm"], check=True, capture_output=True)
    (tmp_path / "in.bin").write_bytes(ref.pack_scheduled(x[0], u[:n], y[:n]))
    subprocess.run([str(exe), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")],
                   check=True)
    got = ref.unpack_scheduled((tmp_path / "out.bin").read_bytes(), 3)
    assert np.array_equal(got.states, want.states) and np.array_equal(got.s, want.s)
    for args, needle in ((["--schedule", "-40", "110", "6"], "--schedule-by"),
                         (["--schedule", "50", "10", "3", "--schedule-by", "T_board"],
                          "LOW < HIGH"),
                         (["--schedule", "-40", "110", "6", "--schedule-by", "T_die"],
                          "T_board"),
                         (["--schedule-by", "T_board"], "--schedule LOW HIGH N")):
        assert main(["export", "--model", str(model), "--rate", "0.5", "--out",
                     str(tmp_path / "bad"), *args, "--quiet"]) == 2, args
        assert needle in capsys.readouterr().err, args
    assert main(["export", "--model", "rtd2", "--rate", "1", "--out", str(tmp_path / "lin"),
                 "--schedule", "0", "50", "3", "--schedule-by", "T_core", "--quiet"]) == 2
    assert "linear" in capsys.readouterr().err
