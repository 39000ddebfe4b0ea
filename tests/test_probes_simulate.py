"""Issue 67, item 1: `simulate` runs the model as written (effects lowered and applied, the
fit's simulator, ETD2 where nonlinear) and refuses what it cannot simulate or what makes
no sense, with exit 2 and a message naming the flag; never a traceback."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from thermojax.cli import main
from thermojax.measurements import read_telemetry

from helpers import CONFIGS
from helpers import run_cli as run, assert_refused as refused

RTD2_TEXT = (CONFIGS / "rtd2.toml").read_text()
LAG = """
[[effects]]
kind = "sensor_offset"
where = ["T_core"]
offset = 0.5

[[effects]]
kind = "sensor_lag"
where = ["T_core"]
time_constant = 3.0
"""
RADIATION = """
[[effects]]
kind = "radiation"
where = ["sheath", "T_fluid"]
coefficient = 2e-10
"""
C1, C2, G12, GB = 0.8, 0.1, 0.08333333333333333, 0.2


def simulated(capsys, tmp_path, text, name, *extra):
    model = tmp_path / f"{name}.toml"
    model.write_text(text)
    out = tmp_path / f"{name}.csv"
    rc, _, err = run(capsys, "simulate", "--model", model, "--profile", "shock", "--out", out,
                     "--quiet", *extra)
    assert rc == 0, err
    return read_telemetry(out)


def reference(ts, t_fluid, k_rad=0.0, tau=None, offset=0.0):
    """rtd2 with its effects, integrated by SciPy from the physics (not the lowered
    matrices): inputs piecewise linear between samples, as the model's default hold."""

    def rate(t, x):
        tf = np.interp(t, ts, t_fluid)
        sheath, core = x[0], x[1]
        q_rad = k_rad * ((tf + 273.15) ** 4 - (sheath + 273.15) ** 4)
        d = [(GB * (tf - sheath) + G12 * (core - sheath) + q_rad) / C1,
             G12 * (sheath - core) / C2]
        if tau is not None:
            d.append((core - x[2]) / tau)
        return d

    x0 = [t_fluid[0]] * (3 if tau is not None else 2)
    sol = solve_ivp(rate, (ts[0], ts[-1]), x0, t_eval=ts, method="LSODA", rtol=1e-10,
                    atol=1e-10, max_step=1.0)
    y = sol.y[2] if tau is not None else sol.y[1]
    return y + offset


def test_sensor_offset_and_lag_are_in_the_output(capsys, tmp_path):
    plain = simulated(capsys, tmp_path, RTD2_TEXT, "plain")
    with_effects = simulated(capsys, tmp_path, RTD2_TEXT + LAG, "lag")
    y0, y1 = plain.channels["T_core"], with_effects.channels["T_core"]
    assert np.abs(y1 - y0).max() > 1.0  # the offset (0.5) and the lag behind the shock
    ref = reference(with_effects.ts, with_effects.channels["T_fluid"], tau=3.0, offset=0.5)
    np.testing.assert_allclose(y1, ref, atol=2e-4)
    np.testing.assert_allclose(y0, reference(plain.ts, plain.channels["T_fluid"]), atol=2e-5)


def test_radiation_runs_the_nonlinear_path(capsys, tmp_path):
    got = simulated(capsys, tmp_path, RTD2_TEXT + RADIATION, "rad", "--states")
    plain = simulated(capsys, tmp_path, RTD2_TEXT, "plain")
    assert np.abs(got.channels["T_core"] - plain.channels["T_core"]).max() > 0.5
    ref = reference(got.ts, got.channels["T_fluid"], k_rad=2e-10)
    np.testing.assert_allclose(got.channels["T_core"], ref, atol=5e-3)  # ETD2, 4 substeps


def test_an_extra_node_is_simulated_and_written_with_states(capsys, tmp_path):
    extra = RTD2_TEXT + """
[[effects]]
kind = "extra_node"
where = ["sheath", "T_fluid"]
name = "film"
capacitance = 0.4
conductance = 0.4
conductance_b = 0.4
"""
    got = simulated(capsys, tmp_path, extra, "extra", "--states")
    plain = simulated(capsys, tmp_path, RTD2_TEXT, "plain")
    assert "state_film" in got.channels
    assert np.abs(got.channels["T_core"] - plain.channels["T_core"]).max() > 0.5


RTD2 = str(CONFIGS / "rtd2.toml")


@pytest.mark.parametrize("extra, flag", [
    (["--power", "1e300"], "--power"),
    (["--power", "1"], "--power"),          # rtd2 has no heat inputs
    (["--dt", "1e-300"], "--dt"),
    (["--seed", "-1", "--noise"], "--seed"),
])
def test_implausible_flags_are_refused_naming_the_flag(capsys, tmp_path, extra, flag):
    out = tmp_path / "x.csv"
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock", "--out", out,
                     *extra)
    refused(rc, err, flag)
    assert not out.exists()


def test_dt_refusal_predicts_the_samples_and_memory(capsys, tmp_path):
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                     "--out", tmp_path / "x.csv", "--dt", "1e-300")
    refused(rc, err, "samples", "memory")


def test_power_with_a_csv_profile_is_refused(capsys, tmp_path):
    chain = str(CONFIGS / "chain3.toml")
    prof = tmp_path / "p.csv"
    assert run(capsys, "simulate", "--model", chain, "--profile", "ramp5", "--out",
               prof)[0] == 0
    rc, _, err = run(capsys, "simulate", "--model", chain, "--profile", prof, "--out",
                     tmp_path / "y.csv", "--power", "0.5")
    refused(rc, err, "--power")


@pytest.mark.parametrize("name", ["", "..", ".", "x" * 300 + ".csv"])
def test_unusable_out_names_are_refused(capsys, tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock", "--out", name)
    refused(rc, err, "--out")


def test_a_dangling_symlink_as_out_is_refused(capsys, tmp_path):
    link = tmp_path / "link.csv"
    link.symlink_to(tmp_path / "nowhere" / "x.csv")
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock", "--out", link)
    refused(rc, err, "--out", "symbolic link")
    assert link.is_symlink()


CHAIN3 = CONFIGS / "chain3.toml"
EFFECTS = {
    "conductance_temperature": 'where = ["pcb", "die"]\nalpha = -0.005',
    "capacitance_temperature": 'where = ["die"]\nbeta = 0.002',
    "heat_source": 'where = ["P_die", "pcb"]\ngain = 0.3',
    "boundary": 'where = ["T_chamber", "pcb"]\nconductance = 0.05',
    "sensor_gain": 'where = ["T_die"]\ngain = 0.01',
    "radiation": 'where = ["housing", "T_chamber"]\ncoefficient = 3e-10',
}


@pytest.fixture(scope="module")
def chain3_plain(tmp_path_factory):
    out = tmp_path_factory.mktemp("plain") / "plain.csv"
    assert main(["simulate", "--model", str(CHAIN3), "--profile", "ramp5", "--power", "0.3",
                 "--out", str(out), "--quiet"]) == 0
    return read_telemetry(out)


@pytest.mark.parametrize("kind", sorted(EFFECTS))
def test_every_effect_kind_changes_the_simulation(capsys, tmp_path, chain3_plain, kind):
    model = tmp_path / f"{kind}.toml"
    model.write_text(CHAIN3.read_text() + f'\n[[effects]]\nkind = "{kind}"\n{EFFECTS[kind]}\n')
    out = tmp_path / "e.csv"
    rc, _, err = run(capsys, "simulate", "--model", model, "--profile", "ramp5", "--power",
                     "0.3", "--out", out, "--quiet")
    assert rc == 0, err
    got = read_telemetry(out)
    diff = max(np.abs(got.channels[c] - chain3_plain.channels[c]).max()
               for c in ("T_housing", "T_die"))
    assert diff > 0.01, (kind, diff)
