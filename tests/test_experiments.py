"""The studies in experiments/ run end to end.

Most studies simulate their own data with thermojax (`tj.simulate`, `thermojax run`'s
`[synthetic]`, `dynamics._lag.first_order_lag`) and fit them with thermojax: what such a
test checks against "the truth that made the data" is a consistency check (a round trip
through one code base, where an error shared by the simulation and the fit cancels),
and the comments say so. Four studies run here on data made outside thermojax by the
tests' `chamber_truth` (`scipy.linalg.expm`; the strain an exact state), swapped in for
the study's own simulation: the three-ramp identification of the six-node IMU, the
headline study's bias recovery, and the viscoelastic study's τ and k, so their
recovery is checked against an independent truth.
"""

import importlib.util
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from chamber_truth import observe, read_chamber_model, simulate

ROOT = Path(__file__).resolve().parents[1]


def load_study(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def scipy_synthetic_runs(spec, syn: dict, folder: Path) -> list[str]:
    """`thermojax run`'s `[synthetic]` runs with the response simulated outside thermojax:
    the same input samples (the built-in chamber profiles, the baseline power and the
    power step between 30 and 60 min, built by thermojax's profile functions: plain
    sampled inputs, written to the CSV), the truth model file read with `tomllib` and
    simulated by `chamber_truth` (exact for the chamber temperature linear and the power
    held between samples), NumPy noise of each sensor's std drawn as `[synthetic]` draws
    it."""
    from thermojax import io

    truth = io.load_model(syn["truth"])
    model = read_chamber_model(syn["truth"])
    assert model.inputs == list(truth.input_columns)
    rng = np.random.default_rng(int(syn.get("seed", 0)))
    paths = []
    for i, name in enumerate(syn["profiles"]):
        prof = io.load_profile(name, dt=float(syn.get("dt", 1.0)))
        u = io.profile_inputs(truth, prof, float(syn.get("power", 0.0)))
        heat = [j for j, c in enumerate(model.inputs) if c in truth.heat_columns]
        u[:, heat] += float(syn.get("power_step", 0.0)) * (
            (prof.ts >= 1800) & (prof.ts < 3600))[:, None]
        clean = observe(model, simulate(model, np.asarray(prof.ts), u), u)
        y = np.column_stack([clean[c] for c in model.sensors])
        stds = np.array([std for _, std in model.sensors.values()])
        y = y + rng.standard_normal(y.shape) * stds
        columns = {c: u[:, j] for j, c in enumerate(model.inputs)}
        columns.update({c: y[:, j] for j, c in enumerate(model.sensors)})
        p = folder / f"synthetic_{i}_{name}.csv"
        io.write_telemetry(p, prof.ts, columns, comments=[f"chamber_truth: profile {name}"])
        paths.append(str(p))
    return paths


@pytest.mark.slow
def test_imu6_three_ramps_study(tmp_path, monkeypatch):
    import thermojax.cli._runner as runner

    monkeypatch.setattr(runner, "synthetic_runs", scipy_synthetic_runs)
    study = load_study("imu6_three_ramps")
    # the recovery table reads the Wald stds: the profile check of 8 of them (~40 s)
    # is tested in tests/test_interval_check.py
    folder = study.main(["--out", str(tmp_path), "--no-interval-check"])
    assert folder.parent == tmp_path
    for name in ("model.toml", "report.json", "recovery.md", "parameter_recovery.png"):
        assert (folder / name).is_file(), name
    report = json.loads((folder / "report.json").read_text())
    simulated_from = study.TRUTH  # configs/imu6.toml, simulated by chamber_truth
    rows = study.recovery_rows(report, __import__("thermojax").load_model(simulated_from))
    identifiable = [r for r in rows if r["std"] is not None]
    # Independent truth: the study's three runs simulated from configs/imu6.toml by
    # chamber_truth (SciPy) with 0.01 °C noise: every identifiable parameter within 4
    # reported std of the truth (a chance of ~1e-3 each if honest).
    assert len(identifiable) >= 12
    assert all(abs(r["error_in_std"]) < 4 for r in identifiable)
    # The proof mass (time constant ~0.06 s against 1 s samples) cannot be determined.
    unidentifiable = {r["name"] for r in rows if r["std"] is None}
    assert "nodes.proof_mass.capacitance" in unidentifiable


def scipy_headline_truth(study, monkeypatch):
    """Replace the headline study's own simulation of the true unit (`tj.simulate` of
    configs/imu6.toml with the proof-mass link at `G_PROOF_MASS`) by `chamber_truth`'s;
    its bias (`true_bias`, plain NumPy from the node temperatures) is kept. Returns the
    number of runs simulated."""
    doc = tomllib.loads(study.IMU.read_text())
    (link,) = [k for k in doc["links"] if k["between"] == ["mems", "proof_mass"]]
    link["conductance"] = study.G_PROOF_MASS
    model = read_chamber_model(doc)
    assert model.inputs == ["T_chamber", "P_asic"]  # the study's input columns
    made = []

    def _simulate(_model, inputs, ts):
        U = np.asarray(inputs)
        z = simulate(model, np.asarray(ts), U)
        out = observe(model, z, U)
        made.append(len(ts))
        return z, np.column_stack([out[c] for c in model.sensors])

    monkeypatch.setattr(study, "_simulate", _simulate)
    return made


def test_imu_bias_headline_study(tmp_path, monkeypatch):
    study = load_study("imu_bias_headline")
    made = scipy_headline_truth(study, monkeypatch)
    out = tmp_path / "headline"
    folder = study.main(["--out", str(out), "--quick"])
    assert folder == out
    for name in ("headline.md", "results.json", "residual_10cpm.png"):
        assert (folder / name).is_file(), name
    with pytest.raises(SystemExit) as refused:  # an existing folder is not overwritten
        study.main(["--out", str(out), "--quick"])
    assert refused.value.code == 2
    res = json.loads((folder / "results.json").read_text())
    rows = res["rows"]
    assert [r["rate_C_per_min"] for r in rows] == [1.0, 5.0, 10.0, 15.0]
    static = [r["static"]["peak"] for r in rows]
    # The static cubic cannot see the gradient term, which grows with the ramp rate.
    assert all(a < b for a, b in zip(static, static[1:])), static
    for r in rows:
        # Static misses most of the gradient term (K_GRAD x the peak gradient of
        # chamber_truth's states).
        assert r["static"]["peak"] > 0.5 * r["peak_gradient_bias_dph"]
        # Exact model, 0.01 °C sensors: the observer leaves < 0.1 °/h (measured ~0.01).
        assert r["observer"]["peak"] < 0.1

    # Independent truth: with no noise, the true unit simulated by chamber_truth (SciPy
    # expm) and an observer of the true model, the observer's innovations are the two
    # simulators' difference (~1e-12 K), so the bias model comes back to roundoff.
    clean = study.study(quick=True, sensor_noise=0.0, bias_noise=0.0, rates=(1.0, 10.0),
                        observers=("observer",))
    truth = list(study.POLY) + [study.K_GRAD]
    assert clean["coefficients"]["observer"] == pytest.approx(truth, rel=1e-6)  # roundoff
    assert clean["calibration"]["observer"]["rms"] < 1e-6  # °/h; roundoff only
    assert clean["rows"][1]["static"]["rms"] > clean["rows"][0]["static"]["rms"]
    assert len(made) >= 7  # every run of both studies came from chamber_truth


def scipy_viscoelastic_truth(study, monkeypatch):
    """Replace the study's own simulation (`tj.simulate`, and the strain by
    `first_order_lag` of the sampled T_mems) by `chamber_truth`: configs/imu6.toml plus
    the study's accelerometer channel and strain, the strain integrated as an exact
    state."""
    doc = tomllib.loads(study.IMU.read_text())
    doc["biases"] = [dict(column=study.COLUMN, temperature=study.NODE,
                          order=len(study.POLY) - 1, coefficients=list(study.POLY),
                          noise=study.BIAS_NOISE)]
    doc["effects"] = [dict(kind="viscoelastic", where=[study.NODE, study.COLUMN],
                           time_constant=study.TAU, k=study.K)]
    model = read_chamber_model(doc)
    assert model.inputs == ["T_chamber", "P_asic"]  # the study's input columns
    n, made = len(model.nodes), {}

    def _simulate(_model, inputs, ts):
        U = np.asarray(inputs)
        z = simulate(model, np.asarray(ts), U)
        out = observe(model, z, U)
        made.update(T=z[:, model.nodes.index(study.NODE)], eps=z[:, n],
                    bias=out[study.COLUMN])
        return z[:, :n], np.column_stack([out[c] for c in model.sensors])

    def true_bias(T_mems, ts):
        np.testing.assert_array_equal(T_mems, made["T"])
        return made["bias"], made["eps"]

    monkeypatch.setattr(study, "_simulate", _simulate)
    monkeypatch.setattr(study, "true_bias", true_bias)
    return made


def test_viscoelastic_hysteresis_study(tmp_path, monkeypatch):
    study = load_study("viscoelastic_hysteresis")
    made = scipy_viscoelastic_truth(study, monkeypatch)
    out = tmp_path / "hysteresis"
    folder = study.main(["--out", str(out), "--quick"])
    assert folder == out
    for name in ("hysteresis.md", "results.json", "hysteresis_loops.png"):
        assert (folder / name).is_file(), name
    with pytest.raises(SystemExit) as refused:  # an existing folder is not overwritten
        study.main(["--out", str(out), "--quick"])
    assert refused.value.code == 2
    res = json.loads((folder / "results.json").read_text())
    assert made  # the data came from chamber_truth
    params = {p["name"]: p for p in res["parameters"]}
    # Independent truth (chamber_truth's data): τ = 1500 s and k = 0.6 µg/K, each within 3
    # reported std.
    for name, truth in (("tau_s", study.TAU), ("k_ug_per_K", study.K)):
        assert params[name]["truth"] == truth
        assert abs(params[name]["value"] - truth) < 3 * params[name]["std"], params[name]
    areas = res["loop_area_ug_C"]
    # The static model's residual keeps the strain's loop (a polynomial encloses nothing:
    # same area as the data's, within the 5 % the observer's estimate error allows) ...
    assert areas["static_residual"] == pytest.approx(areas["true_strain_term"], rel=0.05)
    # ... and the augmented model closes it (measured ~1 %).
    assert areas["augmented_residual"] < 0.1 * areas["static_residual"]


def scipy_phases_truth(study, monkeypatch):
    """Replace the phases study's record (`simulate_record`: `tj.simulate` of
    configs/imu6.toml, the gyro's strain by `first_order_lag` of the sampled T_mems and
    its rate term from thermojax's `A x + B u`) by `chamber_truth`'s: the gyro channel
    (polynomial in the proof mass, the mems-asic gradient, the mems rate, the strain as an
    exact state) evaluated in NumPy; the noise drawn in the study's order. Returns the
    number of records simulated."""
    doc = tomllib.loads(study.IMU.read_text())
    doc["biases"] = [dict(column="gyro", temperature="proof_mass", order=len(study.POLY) - 1,
                          gradients=[["mems", "asic"]], rates=["mems"],
                          coefficients=[*study.POLY, study.K_GRAD, study.K_RATE])]
    doc["effects"] = [dict(kind="viscoelastic", where=["mems", "gyro"],
                           time_constant=study.TAU, k=study.K_STRAIN)]
    model = read_chamber_model(doc)
    assert model.inputs == ["T_chamber", "P_asic"]
    n, made = len(model.nodes), []

    def simulate_record(_model, temperature, ts, rng, sensor_noise=study.SENSOR_NOISE,
                        bias_noise=study.BIAS_NOISE):
        inputs = np.column_stack([temperature, np.full(ts.size, study.P_ASIC)])
        z = simulate(model, np.asarray(ts), inputs)
        out = observe(model, z, inputs)
        clean = np.column_stack([out[c] for c in model.sensors])
        readings = clean + sensor_noise * rng.standard_normal(clean.shape)
        bias = out["gyro"]
        made.append(ts.size)
        return {"ts": ts, "chamber": temperature, "inputs": inputs, "states": z[:, :n],
                "readings": readings, "bias": bias,
                "measured": bias + bias_noise * rng.standard_normal(ts.size),
                "names": list(model.nodes), "sensors": list(model.sensors)}

    monkeypatch.setattr(study, "simulate_record", simulate_record)
    return made


def test_seed_calibration_phases_study(tmp_path, monkeypatch):
    study = load_study("seed_calibration_phases")
    made = scipy_phases_truth(study, monkeypatch)
    out = tmp_path / "phases"
    folder = study.main(["--out", str(out), "--quick"])
    for name in ("phases.md", "results.json", "phase_residuals.png"):
        assert (folder / name).is_file(), name
    text = (folder / "phases.md").read_text()
    for seed_number in ("0.04 °/h", "0.08 °/h", "0.12 °/h", "0.06 °/h"):  # the seed's beside
        assert seed_number in text
    res = json.loads((folder / "results.json").read_text())
    rows = {r["phase"]: r for r in res["rows"]}
    assert list(rows) == ["static_soak", "slow_ramp", "fast_shock", "viscoelastic_dwell"]
    (g,) = rows["slow_ramp"]["identified"]
    # Independent truth from here on: the record comes from chamber_truth (SciPy)
    assert made
    assert abs(g["value"] - 0.5) < 3 * g["std"]  # housing-bulkhead W/K, truth 0.5
    (c,) = rows["fast_shock"]["identified"]
    assert c["value"] == pytest.approx(0.05, rel=0.05)  # MEMS J/K; quick run: 5 %
    tau, k = rows["viscoelastic_dwell"]["identified"]
    assert abs(tau["value"] - study.TAU) < 3 * tau["std"]
    assert abs(k["value"] - study.K_STRAIN) < 3 * k["std"]
    for r in res["rows"]:
        # exact structure: the observer model leaves far less than the 0.02 °/h noise, and
        # the static quadratic (no gradient, rate or strain terms) far more.
        assert r["observer_rms_dph"] < 0.01
        assert r["static_rms_dph"] > 10 * r["observer_rms_dph"]
        assert r["observer_measured_rms_dph"] == pytest.approx(study.BIAS_NOISE, rel=0.1)


def test_allan_compensation_study(tmp_path):
    study = load_study("allan_compensation")
    out = tmp_path / "allan"
    folder = study.main(["--out", str(out), "--quick"])
    for name in ("allan.md", "results.json", "allan_deviation.png", "gyro_output.png"):
        assert (folder / name).is_file(), name
    res = json.loads((folder / "results.json").read_text())
    p = res["noise_parameters"]
    # The raw output's ARW recovers the injected white noise within its (68 %) interval,
    # widened by 2 % for the flicker's share at τ ≈ 1 s.
    value, lower, upper = p["raw"]["arw_deg_per_sqrt_h"]
    assert 0.98 * lower <= study.ARW <= 1.02 * upper
    # The observer-compensated curve is the noise's own; the raw one drifts up.
    assert p["observer"]["bias_instability_dph"][0] == pytest.approx(
        p["noise_only"]["bias_instability_dph"][0], rel=0.05)
    assert p["raw"]["adev_at_longest_tau_dph"] > 3 * p["observer"]["adev_at_longest_tau_dph"]
    assert p["static"]["thermal_residual_rms_dph"] > 10 * p["observer"]["thermal_residual_rms_dph"]


@pytest.mark.slow
def test_unit_variance_procurement_study(tmp_path):
    """The procurement study (--quick: 16 units per preset, a short profile). Consistency
    checks (each unit is simulated by thermojax, as in tests/test_montecarlo.py, whose
    `test_fit_recovers_units_simulated_by_scipy` checks the fit on SciPy-made units):
    a unit's own model bounds every method; the nominal observer's
    median error and secondary-state offset grow with the preset's spread (its only error
    is the unit's deviation, 5 → 32 % on every capacitance and conductance); a unit's own
    fit gets close to its own model's bound, far below the nominal's; the own observer
    overshoots nothing; the end-of-line trims do better than nominal at the widest
    spread."""
    study = load_study("unit_variance_procurement")
    folder = study.main(["--out", str(tmp_path / "procurement"), "--quick"])
    for name in ("procurement.md", "results.json", "procurement.png", "observer_impact.png"):
        assert (folder / name).is_file(), name
    res = json.loads((folder / "results.json").read_text())
    assert list(res) == ["asic_integrated", "oem_module", "bare_die_custom",
                         "thermistor_custom_housing"]
    nominal = [res[p]["bias_peak"]["nominal"]["p50"] for p in res]
    assert nominal == sorted(nominal) and nominal[-1] > 3 * nominal[0]
    for p, r in res.items():
        peak, within = r["bias_peak"], r["within_spec"]
        assert within["fitted"] >= within["nominal"] and within["own"] == 1.0, p
        assert peak["own"]["p50"] <= peak["fitted"]["p50"] < 0.2 * peak["nominal"]["p50"], p
        # the unit's own observer on noise-free readings from the true steady state tracks
        # the true trajectory exactly: its step overshoot is roundoff
        assert r["step_overshoot"]["own"]["max"] < 1e-9, p
        assert r["phase_loss"]["own"]["max"] < 1e-9, p   # X̂ = X in the frequency domain
    # the secondary state's offset under the nominal observer grows with the spread
    offset = [res[p]["temp_offset"]["nominal"]["p50"] for p in res]
    assert offset == sorted(offset)
    # the end-of-line trims (two factors from a 15-16 min test) beat nominal at 32 %
    wide = res["thermistor_custom_housing"]
    for m in ("trim_step", "trim_sweep"):
        assert wide["within_spec"][m] >= wide["within_spec"]["nominal"], m
        assert wide["bias_peak"][m]["p50"] < 0.8 * wide["bias_peak"]["nominal"]["p50"], m


@pytest.mark.slow
def test_ten_year_ageing_study(tmp_path):
    """One unit (--quick ages 0, 5, 10 y): the factory observer's error grows as the
    conductances age, the adaptive filter ends within 2 % of the aged conductances (the
    values the study simulated with thermojax: a consistency check) and keeps the bias
    within the tactical 0.5 °/h."""
    study = load_study("ten_year_ageing")
    folder = study.main(["--out", str(tmp_path / "ageing"), "--quick", "--units", "1"])
    for name in ("ageing.md", "results.json", "ageing.png"):
        assert (folder / name).is_file(), name
    res = json.loads((folder / "results.json").read_text())
    unit = res["per_unit"][0]
    factory = unit["factory"]
    assert res["ages_years"] == [0.0, 5.0, 10.0]
    assert factory[0] < 0.01 and factory[0] < factory[1] < factory[2]
    assert max(unit["adaptive"]) < res["spec_dph"]
    assert all(abs(r - 1) < 0.02 for ratios in unit["adaptive_ratio"] for r in ratios)
    assert unit["recalibrated"][2] < factory[2]   # recalibrated at 8 y, not at 0


def test_prbs1_forward_selection_tests_each_step_as_the_paper_and_needs_its_data(
        tmp_path, capsys):
    from scipy import stats

    study = load_study("prbs1_forward_selection")
    lr, df, p = study.lr_test({"nll": -100.0, "n_params": 6}, {"nll": -110.0, "n_params": 9})
    assert (lr, df) == (20.0, 3) and p == pytest.approx(stats.chi2.sf(20.0, 3))
    study.DATA = tmp_path / "absent"  # the real data live beside the repository only
    assert study.main(["--out", str(tmp_path / "out")]) == 2
    assert "PRBS1 data are not at" in capsys.readouterr().err
