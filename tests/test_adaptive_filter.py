"""The adaptive extended Kalman filter (issue 35, item 4) against an independent simulator,
in JAX (the study version) and for firmware (the NumPy reference and its C, bit for bit).

A three-node sensor module (die on a board in a case, the chamber outside) whose
die-attach conductance drifts or steps. The truth is simulated here in NumPy/SciPy:
`scipy.linalg.expm` of each sample period's system at the conductance of the period's
middle (the drift is hours, a period two seconds), the power held, the chamber held.
"""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
import scipy.linalg

import thermojax.reference as ref
from thermojax.io import parse_model
from thermojax.observer import adaptive_design, track_conductances

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
hold = "zoh"
[[heat_inputs]]
node = "die"
input = "P_die"
hold = "zoh"
[[sensors]]
node = "die"
column = "T_die"
noise = 0.01
[[sensors]]
node = "board"
column = "T_board"
noise = 0.01
"""
DT = 2.0
ATTACH = "links.die-board.conductance"
NOISE = 0.01


def truth(g_attach, seconds, seed=0, chamber=True, power=True):
    """Independent simulation: node temperatures (T, 3) and readings (T, 2) for a die
    attach conductance `g_attach(t)` W/K; chamber and power as held inputs (T, 2)."""
    t = np.arange(int(seconds / DT)) * DT
    T_ch = 25.0 + 20.0 * np.sin(2 * np.pi * t / 7200.0) if chamber else np.full(t.size, 25.0)
    P = 0.2 * ((t // 300) % 2) if power else np.zeros(t.size)
    u = np.stack([T_ch, P], axis=1)
    Cap = np.array([0.5, 5.0, 50.0])
    x = np.empty((t.size, 3))
    x[0] = T_ch[0] + P[0] * np.array([1 / 0.05 + 1 / 0.5 + 1.0, 1 / 0.5 + 1.0, 1.0])
    for k in range(t.size - 1):
        g = g_attach(t[k] + DT / 2)
        K = np.array([[g, -g, 0.0], [-g, g + 0.5, -0.5], [0.0, -0.5, 1.5]])
        A = -K / Cap[:, None]
        B = np.array([[0.0, 1.0], [0.0, 0.0], [1.0, 0.0]]) / Cap[:, None]
        M = scipy.linalg.expm(np.block([[A, B], [np.zeros((2, 5))]]) * DT)
        x[k + 1] = M[:3, :3] @ x[k] + M[:3, 3:] @ u[k]
    y = x[:, :2] + NOISE * np.random.default_rng(seed).standard_normal((t.size, 2))
    return t, u, x, y


@pytest.fixture(scope="module")
def spec():
    return parse_model(MODEL)


def test_it_follows_a_drifting_die_attach_within_its_stated_uncertainty(spec):
    """Die attach 0.05 → 0.035 W/K over 6 h (−30 %, voiding): the filter, started at the
    nominal 0.05, follows it: after the first half hour the truth lies within the 3σ band
    at ≥ 95 % of samples, and the end estimate is within 2 % and 3σ."""
    hours = 6.0
    g = lambda s: 0.05 * (1.0 - 0.3 * s / (hours * 3600))  # noqa: E731
    t, u, x, y = truth(g, hours * 3600)
    run = track_conductances(spec, [ATTACH], u, y, DT, drift=2e-3, ceiling=0.5)
    est, sd = run.conductances[:, 0], run.log_std[:, 0]
    z = np.log(est / g(t)) / sd
    settled = t > 1800
    assert np.mean(np.abs(z[settled]) < 3) >= 0.95, np.abs(z[settled]).max()
    assert abs(est[-1] / g(t[-1]) - 1) < 0.02 and abs(z[-1]) < 3
    assert np.all(np.abs(run.states - x).max(0)[:2] < 5 * NOISE)
    assert not run.flags.any()  # a slow drift is what the random walk expects
    # without tracking (the nominal attach) the die estimate drifts from the truth
    frozen = track_conductances(spec, [ATTACH], u, y, DT, drift=0.0, ceiling=1e-9)
    assert np.abs(frozen.states - x)[-3600:, 0].max() > 3 * np.abs(run.states - x)[-3600:,
                                                                                      0].max()


def test_its_covariance_stays_bounded_through_a_long_dwell(spec):
    """Ten hours at a constant chamber and no power: no heat flows through the attach and
    nothing informs it. Its log std rises to the ceiling and no further; the estimate
    stays finite and where it was; the temperatures stay at the truth."""
    t, u, x, y = truth(lambda s: 0.05, 10 * 3600, seed=1, chamber=False, power=False)
    run = track_conductances(spec, [ATTACH], u, y, DT, drift=2e-3, ceiling=0.3)
    sd = run.log_std[:, 0]
    assert np.all(np.isfinite(run.conductances)) and np.all(np.isfinite(run.states))
    assert sd.max() <= 0.3 * (1 + 1e-9)
    assert sd[-1] > 0.25  # it did rise: the dwell carries no information on the attach
    assert np.abs(np.log(run.conductances[:, 0] / 0.05)).max() < 0.05
    assert np.abs(run.states - x)[t > 1800].max() < 5 * NOISE  # the unmeasured case settled
    assert not run.flags.any()
    # the gate is what holds it: corrected on every sample, the estimate wanders on noise
    ungated = track_conductances(spec, [ATTACH], u, y, DT, drift=2e-3, ceiling=0.3,
                                 excitation=0.0)
    assert np.abs(np.log(ungated.conductances[:, 0] / 0.05)).max() > 0.2


def test_it_flags_a_delaminating_die_attach_and_relearns_it(spec):
    """The attach halves at 3 h (a delamination): no flag before it, a flag within five
    minutes after, and with the covariance reset the estimate reaches the new value within
    3σ (and 5 %) half an hour later."""
    step = 3 * 3600.0
    g = lambda s: 0.05 if s < step else 0.025  # noqa: E731
    t, u, x, y = truth(g, 5 * 3600, seed=2)
    run = track_conductances(spec, [ATTACH], u, y, DT, drift=2e-4, ceiling=0.5)
    first = t[run.flags]
    assert first.size and first[0] >= step, first[:3]
    assert first[0] - step <= 300.0, first[0] - step
    later = t >= first[0] + 1800
    est, sd = run.conductances[later, 0], run.log_std[later, 0]
    assert np.all(np.abs(np.log(est / 0.025)) < 3 * sd) or np.all(np.abs(est / 0.025 - 1)
                                                                   < 0.05)
    assert abs(est[-1] / 0.025 - 1) < 0.05


def test_mistakes_are_named(spec):
    t, u, x, y = truth(lambda s: 0.05, 600)
    with pytest.raises(ValueError, match="links.die-board.conductance"):
        track_conductances(spec, ["links.die-case.conductance"], u, y, DT, drift=1e-3)
    y_bad = y.copy()
    y_bad[17, 1] = np.nan
    with pytest.raises(ValueError, match="sample 17"):
        track_conductances(spec, [ATTACH], u, y_bad, DT, drift=1e-3)


# -- the firmware version: NumPy reference and C --------------------------------------------

def test_the_firmware_filter_follows_the_drift_like_the_study_version(spec):
    """`AdaptiveReference` (Tustin substeps, conductances in W/K, plain float64) on the
    drifting attach: the truth within its 3σ at ≥ 95 % of samples after half an hour, the
    end within 1 %, and the study version (matrix exponential, logs) within 2 %."""
    hours = 3.0
    g = lambda s: 0.05 * (1.0 - 0.3 * s / (hours * 3600))  # noqa: E731
    t, u, x, y = truth(g, hours * 3600, seed=3)
    design = adaptive_design(spec, [ATTACH], DT, drift=2e-3, ceiling=0.5)
    run = ref.AdaptiveReference(design).run(x[0], u, y)
    z = (run.conductances[:, 0] - g(t)) / np.sqrt(run.variances[:, 3])
    settled = t > 1800
    assert np.mean(np.abs(z[settled]) < 3) >= 0.95
    assert abs(run.conductances[-1, 0] / g(t[-1]) - 1) < 0.01
    assert np.abs(run.states - x)[settled].max() < 5 * NOISE
    study = track_conductances(spec, [ATTACH], u, y, DT, drift=2e-3, ceiling=0.5, x0=x[0])
    assert np.abs(study.conductances[settled, 0] / run.conductances[settled, 0] - 1).max() \
        < 0.02


def test_the_firmware_filter_in_c_is_bit_exact(spec, tmp_path):
    """The generated C against `AdaptiveReference`, bit for bit (states, conductances,
    covariance diagonal, NIS, flags), at -O2 and -O3: a first-order-hold chamber, three
    Tustin substeps, the attach and the case's boundary tracked, through a delamination
    that is flagged and reacquired."""
    foh = parse_model(MODEL.replace('hold = "zoh"', 'hold = "foh"', 1))
    design = adaptive_design(foh, [ATTACH, "boundaries.case-T_chamber.conductance"], DT,
                             drift=[2e-4, 1e-4], ceiling=[0.5, 0.3], substeps=3)
    assert design.holds == ("foh", "zoh")
    t, u, x, y = truth(lambda s: 0.05 if s < 3600 else 0.025, 2 * 3600, seed=4)
    want = ref.AdaptiveReference(design).run(x[0], u, y)
    assert want.flags.any() and not want.flags[t < 3600].any()
    src = ref.generate_adaptive_c(design, "tj_adaptive")
    for name, text in (("tj_adaptive.h", src.header), ("tj_adaptive.c", src.source),
                       ("main.c", src.harness)):
        (tmp_path / name).write_text(text)
    (tmp_path / "in.bin").write_bytes(ref.pack_adaptive(x[0], u, y))
    for opt in ("-O2", "-O3"):
        exe = tmp_path / f"prog{opt}"
        subprocess.run(["gcc", "-std=c99", opt, "-Wall", "-Wextra", "-pedantic", "-Werror",
                        "-ffp-contract=off", "-o", str(exe), str(tmp_path / "tj_adaptive.c"),
                        str(tmp_path / "main.c"), "-lm"], check=True, capture_output=True)
        subprocess.run([str(exe), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")],
                       check=True)
        got = ref.unpack_adaptive((tmp_path / "out.bin").read_bytes(), 3, 2)
        for field in ("states", "conductances", "variances", "nis", "flags"):
            assert np.array_equal(getattr(got, field), getattr(want, field)), (opt, field)


def test_export_writes_the_adaptive_filter_and_its_c_plays_back_bit_exact(tmp_path, capsys):
    """`thermojax export --adaptive ... --adaptive-drift ...`: the artifact's design is
    `adaptive_design`'s, `load_observer(DIR).adaptive_reference()` rebuilds the filter
    from `observer.json`, and the artifact's own C file plays back bit-exact with it."""
    from thermojax.cli import main

    model = tmp_path / "module3.toml"
    model.write_text(MODEL)
    out = tmp_path / "obs"
    assert main(["export", "--model", str(model), "--rate", str(1 / DT), "--out", str(out),
                 "--adaptive", ATTACH, "--adaptive-drift", "2e-4", "--quiet"]) == 0
    assert "adaptive filter: tracks links.die-board.conductance" in capsys.readouterr().out
    art = ref.load_observer(out)
    filt = art.adaptive_reference()
    assert filt.d == adaptive_design(parse_model(MODEL), [ATTACH], DT, drift=2e-4,
                                     ceiling=0.5)
    t, u, x, y = truth(lambda s: 0.05 if s < 1800 else 0.03, 3600, seed=5)
    want = filt.run(x[0], u, y)
    assert want.flags.any()
    exe = tmp_path / "prog"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-ffp-contract=off", "-o", str(exe), str(out / "tj_adaptive.c"),
                    str(out / "tj_adaptive_main.c"), "-lm"], check=True, capture_output=True)
    (tmp_path / "in.bin").write_bytes(ref.pack_adaptive(x[0], u, y))
    subprocess.run([str(exe), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")],
                   check=True)
    got = ref.unpack_adaptive((tmp_path / "out.bin").read_bytes(), 3, 1)
    for field in ("states", "conductances", "variances", "nis", "flags"):
        assert np.array_equal(getattr(got, field), getattr(want, field)), field
    # the mistakes a user makes, each named
    assert main(["export", "--model", str(model), "--rate", "1", "--out",
                 str(tmp_path / "a"), "--adaptive", ATTACH, "--quiet"]) == 2
    assert "--adaptive-drift" in capsys.readouterr().err
    assert main(["export", "--model", str(model), "--rate", "1", "--out",
                 str(tmp_path / "b"), "--adaptive", "links.die-case.conductance",
                 "--adaptive-drift", "1e-4", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "links.die-board.conductance" in err and "--adaptive" in err
