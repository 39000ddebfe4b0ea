"""The calibration pipeline and `thermojax calibrate` (issue 13 item 3).

Truth made outside thermojax: configs/imu6_bias.toml simulated by the tests' own
`chamber_truth` (NumPy and `scipy.linalg.expm`, no thermojax import; temperature log every
2 s, inertial log at 5 Hz on its own clock, noise and outliers) through the example's
chamber programmes; the pipeline starts from configs/calibration/imu6_bias_start.toml
(conductances off the truth, bias coefficients unknown). The truth's values are read
from the model file with `tomllib`. thermojax's own generator of the same logs
(`synthetic_imu_logs`, the data of `thermojax calibrate --make-example-data`) is checked
against `chamber_truth` in `test_synthetic_logs_match_the_scipy_truth`.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from chamber_truth import chamber_logs, read_chamber_model
from helpers import CONFIGS

from thermojax.calibration import run_pipeline
from thermojax.calibration._synthetic import (EXAMPLE_RUNS, TRANSIENT_PROGRAMME,
                                              synthetic_imu_logs)
from thermojax.cli._main import main

EXAMPLE = CONFIGS / "calibration" / "imu6_bias.toml"
N_SIGMA = 3.0  # "within the reported uncertainty": a 3σ band


def generator_truth():
    """The truth `chamber_truth` simulates (configs/imu6_bias.toml, read with `tomllib`):
    channel -> {term name: value}, and the viscoelastic time constants (s)."""
    doc = tomllib.loads((CONFIGS / "imu6_bias.toml").read_text())
    truth, taus = {}, {}
    for b in doc["biases"]:
        names = ([f"poly{k}" for k in range(b["order"] + 1)]
                 + [f"gradient.{a}-{c}" for a, c in b.get("gradients", [])]
                 + [f"rate.{n}" for n in b.get("rates", [])])
        truth[b["column"]] = dict(zip(names, b["coefficients"]))
    for e in doc["effects"]:
        node, column = e["where"]
        truth[column][f"viscoelastic.{node}.k"] = e["k"]
        taus[column] = e["time_constant"]
    return truth, taus


TRUTH, TAUS = generator_truth()


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """The example config and model in a folder with scaled-down logs simulated by
    `chamber_truth` (SciPy) through the example's programmes (plain tuples of chamber
    set points)."""
    root = tmp_path_factory.mktemp("calibration")
    shutil.copy(EXAMPLE, root / "imu6_bias.toml")
    shutil.copy(EXAMPLE.parent / "imu6_bias_start.toml", root / "imu6_bias_start.toml")
    truth = chamber_logs(root / "data", CONFIGS / "imu6_bias.toml", EXAMPLE_RUNS,
                         temperature_dt_s=2.0, inertial_rate_hz=5.0)
    return root, truth


def test_synthetic_logs_match_the_scipy_truth(tmp_path):
    """thermojax's example-data generator (its reference observer's discretization and
    `BiasEvaluator`) against `chamber_truth` (expm of the augmented system, NumPy bias
    terms) on one short run, with the same seed: the same files to roundoff, except the
    accelerometer's strain term, which `BiasEvaluator` discretizes for the MEMS
    temperature linear between samples where `chamber_truth` integrates the strain
    state exactly (measured 2.5e-5 µg at 2 s samples, against 50 µg of noise)."""
    runs = {"short": TRANSIENT_PROGRAMME[:3]}
    kw = dict(temperature_dt_s=2.0, inertial_rate_hz=5.0)
    ours = chamber_logs(tmp_path / "scipy", CONFIGS / "imu6_bias.toml", runs, **kw)["short"]
    theirs = synthetic_imu_logs(tmp_path / "tj", model=CONFIGS / "imu6_bias.toml", runs=runs,
                                **kw)["short"]
    n = len(read_chamber_model(CONFIGS / "imu6_bias.toml").nodes)
    np.testing.assert_array_equal(ours.ts, theirs.ts)
    np.testing.assert_allclose(theirs.states, ours.states[:, :n], rtol=0, atol=1e-9)
    np.testing.assert_allclose(theirs.bias["gyro_x_dph"], ours.bias["gyro_x_dph"], rtol=0,
                               atol=1e-9)
    np.testing.assert_allclose(theirs.bias["accel_x_ug"], ours.bias["accel_x_ug"], rtol=0,
                               atol=1e-3)
    for c in ours.outlier_rows:
        np.testing.assert_array_equal(theirs.outlier_rows[c], ours.outlier_rows[c])
    for f, atol in (("temperature_file", 1e-9), ("inertial_file", 1e-3)):
        a, b = (np.genfromtxt(getattr(r, f), delimiter=",", names=True, skip_header=1)
                for r in (ours, theirs))
        assert a.dtype.names == b.dtype.names
        for name in a.dtype.names:
            np.testing.assert_allclose(b[name], a[name], rtol=0, atol=atol, err_msg=name)


def with_config(root: Path, name: str, edit) -> Path:
    text = edit((root / "imu6_bias.toml").read_text())
    (root / name).write_text(text)
    return root / name


@pytest.fixture(scope="module")
def results(example):
    root, _ = example
    # at 5 Hz the accelerometer's 50 µg white noise leaves ~6 µg after the 0.04 Hz low-pass
    cfg = with_config(root, "loose.toml", lambda t: t.replace("rms = 5.0", "rms = 10.0")
                      .replace("peak = 20.0", "peak = 40.0"))
    return run_pipeline(cfg, observer_dir=root / "observer")


def test_known_truth_recovered(results):
    res = results
    # (a) every injected outlier is among the replaced samples
    assert all(n >= 5 for n in res.stages[0]["outliers"].values())
    # (b) the gyro's static polynomial (P_asic = 0 on the dwells: every node at one
    # temperature, so the sensor indexes the proof mass)
    p = res.static["gyro_x_dph"].polynomial
    gyro_poly = [TRUTH["gyro_x_dph"][f"poly{k}"] for k in range(4)]
    assert len(res.static["gyro_x_dph"].plateaus) >= 5
    np.testing.assert_array_less(np.abs(p.coefficients - gyro_poly), N_SIGMA * p.std)
    # (c) the joint fit's polynomials (the accelerometer's plateaus carry strain that has
    # not relaxed, so its static polynomial is not the truth; the joint fit's is)
    k = res.coupling
    for c in ("gyro_x_dph", "accel_x_ug"):
        for name, t in TRUTH[c].items():
            if name.startswith("poly"):
                v, s = k.polynomial[c][name]
            else:  # (d) the coupling matrix: gradient, rate and strain coefficients
                i, j = k.channels.index(c), k.regressors.index(name)
                v, s = k.matrix[i, j], k.std[i, j]
            print(f"{c} {name}: {v:.6g} ± {s:.2g} (truth {t:g}, {(v - t) / s:+.2f} σ)")
            assert np.isfinite(s) and abs(v - t) < N_SIGMA * s, (c, name, v, s, t)
    # the stds account for the low-passed noise's correlation (≈ 1.18 at cutoff 0.8)
    assert 1.1 < k.noise_factor < 1.3
    tau, tau_std = k.time_constants["accel_x_ug"]["viscoelastic.mems"]
    tol = N_SIGMA * tau_std if tau_std is not None else 0.1 * TAUS["accel_x_ug"]
    assert abs(tau - TAUS["accel_x_ug"]) < tol, (tau, tau_std)
    # (e) verification passes on the held-back run with a spec above the noise
    assert res.passed and {c.channel for c in res.checks} == {"gyro_x_dph", "accel_x_ug"}


def thermal_truth() -> dict:
    """The thermal parameters `chamber_truth` simulated, read with `tomllib`, under the
    names the thermal-fit stage reports."""
    doc = tomllib.loads((CONFIGS / "imu6_bias.toml").read_text())
    v = lambda x: x["value"] if isinstance(x, dict) else x  # noqa: E731
    truth = {f"nodes.{n['name']}.capacitance": v(n["capacitance"]) for n in doc["nodes"]}
    truth.update({f"links.{'-'.join(k['between'])}.conductance": v(k["conductance"])
                  for k in doc["links"]})
    truth.update({f"boundaries.{b['node']}-{b['input']}.conductance": v(b["conductance"])
                  for b in doc["boundaries"]})
    truth.update({f"effects.viscoelastic.{e['where'][0]}-{e['where'][1]}.time_constant":
                  e["time_constant"] for e in doc["effects"]})
    return truth


def test_thermal_fit_stds_with_correlated_residuals(example, results):
    """The thermal parameters of the joint fit against the generator's truth, in the
    Newey-West stds the stage reports beside the white-noise ones.

    At the example's dt_s = 10 s (a 0.04 Hz low-pass of logs taken every 2 s) the ASIC
    sensor's residuals are correlated (lag-1 ≈ 0.77: its power steps put content between
    samples that first-order-hold inputs miss) and the stage says so; the housing
    boundary conductance is then 3.7 Newey-West stds (6e-5 relative) off the truth.
    At dt_s = 4 s every residual is just filtered noise (lag-1 ≈ 0.3) and every thermal
    parameter is within 3 stds of the truth."""
    stage = next(st for st in results.stages if st["stage"] == "thermal_fit")
    rho = stage["residual_autocorrelation"]
    assert rho["T_asic"] > 0.6 and all(0.1 < v < 0.45 for c, v in rho.items() if c != "T_asic")
    root, _ = example
    cfg = with_config(root, "dt4.toml", lambda t: t.replace("dt_s = 10.0", "dt_s = 4.0").replace(
        '"condition", "static_polynomial", "thermal_fit", "coupling", "verify"',
        '"condition", "thermal_fit"'))
    stage = next(st for st in run_pipeline(cfg).stages if st["stage"] == "thermal_fit")
    assert all(0.1 < v < 0.45 for v in stage["residual_autocorrelation"].values())
    truth, checked = thermal_truth(), 0
    for name, p in stage["parameters"].items():
        if "std_hac" not in p or name.startswith("biases.") or name.endswith(".initial"):
            continue  # the runs' starts, estimated from the data, are not in the truth file
        t, s = truth[name], p["std_hac"]
        print(f"{name}: {p['value']:.6g} ± {p['std']:.2g} (Newey-West ± {s:.2g}), truth {t:g}")
        # filtered noise: the corrected stds are larger, by less than 2x
        assert p["std"] < s < 2 * p["std"], (name, p)
        assert abs(p["value"] - t) < N_SIGMA * s, (name, p, t)
        checked += 1
    assert checked == 5  # four conductances and the strain's time constant


def test_verification_fails_below_the_noise(example, results):
    root, _ = example
    res = results
    tight = with_config(root, "tight.toml", lambda t: t.replace("rms = 0.05", "rms = 0.005")
                        .replace("rms = 5.0", "rms = 10.0").replace("peak = 20.0", "peak = 40.0"))
    from thermojax.calibration._config import load_config
    from thermojax.calibration._pipeline import verify

    config = load_config(tight)
    held = [r for r in res.runs if r.use == "verification"]
    checks = verify(res.calibrated_spec, held, config, root / "observer_tight")
    by = {c.channel: c for c in checks}
    assert not by["gyro_x_dph"].passed and by["gyro_x_dph"].rms > 0.005
    assert by["accel_x_ug"].passed


def oadev(y: np.ndarray, m: int) -> float:
    """Overlapping Allan deviation by its definition (NIST SP 1065 eq. 11), written
    independently of allantools: phase `x = cumsum(y)` (in sample periods), `σ²(mτ₀) =
    Σ (x_{i+2m} − 2 x_{i+m} + x_i)² / (2 m² (N − 2m))` over the `N − 2m` overlapping
    second differences of the `N = len(y) + 1` phase points."""
    x = np.concatenate([[0.0], np.cumsum(y)])
    d = x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]
    return float(np.sqrt(np.mean(d ** 2) / (2 * m ** 2)))


def test_oadev_textbook():
    """The test's own oadev on white noise: σ(τ) = σ_sample / √m."""
    y = np.random.default_rng(3).standard_normal(200_000)
    for m in (1, 4, 16):
        assert oadev(y, m) == pytest.approx(1 / np.sqrt(m), rel=0.03)


def test_verification_allan(results, tmp_path):
    """The gyro's Allan deviation on the held-back run: figure, report numbers equal to an
    independent computation on the same series, and the noise the truth injected."""
    from thermojax.calibration import write_results

    res = results
    written = write_results(res, tmp_path)
    png = tmp_path / "allan_gyro_x_dph.png"
    assert written["allan_gyro_x_dph.png"] == png
    head = png.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
    assert int.from_bytes(head[16:20], "big") >= 1200  # px wide
    assert not (tmp_path / "allan_accel_x_ug.png").exists()  # gyro channels only
    report = json.loads((tmp_path / "report.json").read_text())
    rows = report["stages"][-1]["allan"]
    assert [(r["run"], r["channel"], r["rate_unit"]) for r in rows] == [
        ("holdout", "gyro_x_dph", "deg/h")]
    row = rows[0]
    check = next(c for c in res.checks if c.channel == "gyro_x_dph")
    keep = np.isfinite(check.residual)
    assert keep.sum() == check.ts.size - 30  # skip_s = 300 s of a 10 s base
    series = {"raw": check.measured[keep], "static polynomial": check.static_residual[keep],
              "observer": check.residual[keep]}
    assert list(row["outputs"]) == list(series)
    for name, y in series.items():
        o = row["outputs"][name]
        ms = np.round(np.asarray(o["taus_s"]) / res.config.dt_s).astype(int)
        assert ms[0] == 1 and np.all(ms[1:] == 2 * ms[:-1])  # octaves from dt_s
        np.testing.assert_allclose(o["adev"], [oadev(y, m) for m in ms], rtol=1e-9)
        assert np.all(np.asarray(o["lower"]) < o["adev"]) and np.all(np.asarray(o["upper"])
                                                                     > o["adev"])
        k = int(np.argmin(o["adev"]))
        bi = o["bias_instability"]
        assert bi["value"] == pytest.approx(o["adev"][k] / 0.664)
        assert bi["lower"] < bi["value"] < bi["upper"] and bi["tau_s"] == o["taus_s"][k]
    raw, static, obs = (row["outputs"][k] for k in series)
    # the truth: white noise 10 × 0.02 °/h per 5 Hz inertial sample, N = 0.2/√5 °/h·√s;
    # the observer-compensated output is that noise (read where the slope is −1/2)
    truth_arw = 0.2 / np.sqrt(5.0)
    arw = obs["angle_random_walk"]
    assert arw is not None and arw["lower"] < arw["value"] < arw["upper"]
    assert arw["value"] == pytest.approx(truth_arw, rel=0.1)
    assert obs["angle_random_walk_deg_per_sqrt_h"]["value"] == pytest.approx(arw["value"] / 60)
    # raw and static outputs carry the thermal drift: no −1/2 slope, or a worse one
    for other in (raw, static):
        assert (other["angle_random_walk"] is None
                or other["angle_random_walk"]["value"] >= arw["value"])
        assert other["adev"][-1] > 10 * obs["adev"][-1]
        assert other["bias_instability"]["value"] > obs["bias_instability"]["value"]
    assert raw["adev"][-1] > static["adev"][-1]  # the polynomial removes the slow part
    md = (tmp_path / "report.md").read_text()
    assert "Overlapping Allan deviation" in md
    assert "| holdout | gyro_x_dph (deg/h) | observer |" in md


@pytest.mark.slow
def test_cli_end_to_end(example):
    root, _ = example
    cfg = with_config(root, "cli.toml", lambda t: t.replace("rms = 5.0", "rms = 10.0")
                      .replace("peak = 20.0", "peak = 40.0"))
    out = root / "results"
    proc = subprocess.run([sys.executable, "-m", "thermojax", "calibrate", str(cfg), "--out",
                           str(out)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    for stage in ("condition", "static_polynomial", "thermal_fit", "coupling", "verify"):
        assert f"{stage}:" in proc.stdout
    for name in ("report.json", "report.md", "model_calibrated.toml", "static_polynomial.png",
                 "verification_residual.png", "allan_gyro_x_dph.png",
                 "observer/observer.json", ".thermojax"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert report["schema"] == 1 and report["thermojax_version"]
    assert [s["stage"] for s in report["stages"]] == ["condition", "static_polynomial",
                                                     "thermal_fit", "coupling", "verify"]
    assert report["passed"] is True
    assert report["stages"][-1]["allan"][0]["channel"] == "gyro_x_dph"
    assert "Allan deviation" in proc.stdout
    from thermojax.io import load_model

    assert load_model(out / "model_calibrated.toml").biases[0].coefficients is not None
    # a folder thermojax did not write is refused without --force
    foreign = root / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(["calibrate", str(cfg), "--out", str(foreign), "--quiet"]) == 2


# ---------------------------------------------------------------------------
# Bad input: exit 2, a message naming the thing, no traceback


def _fails(capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for n in needles:
        assert n in err, (n, err)
    return err


def _edit_csv(src: Path, dst: Path, fn):
    lines = src.read_text().splitlines()
    dst.write_text("\n".join(fn(lines)) + "\n")


def test_bad_config(example, capsys, tmp_path):
    root, _ = example
    cfg = with_config(root, "bad_stage.toml",
                      lambda t: t.replace('"coupling", "verify"]', '"coupling", "polish"]'))
    _fails(capsys, ["calibrate", str(cfg), "--out", str(tmp_path / "o")], "bad_stage.toml",
           "'stages'", "polish")
    cfg = with_config(root, "bad_channel.toml",
                      lambda t: t.replace('"accel_x_ug"]', '"gyro_z_dph"]'))
    _fails(capsys, ["calibrate", str(cfg), "--out", str(tmp_path / "o")], "bad_channel.toml",
           "'channels'", "gyro_z_dph")
    cfg = with_config(root, "bad_file.toml", lambda t: t.replace("data/holdout_inertial.csv",
                                                                 "data/nowhere.csv"))
    _fails(capsys, ["calibrate", str(cfg), "--out", str(tmp_path / "o")], "bad_file.toml",
           "runs[2].inertial", "nowhere.csv")
    # dwells must last 2900 s: only the three long ones of the plateau run qualify
    cfg = with_config(root, "bad_order.toml", lambda t: t.replace("min_duration_s = 1200.0",
                                                                  "min_duration_s = 2900.0"))
    err = _fails(capsys, ["calibrate", str(cfg), "--out", str(tmp_path / "o")],
                 "bad_order.toml", "static_polynomial.order", "dwell plateau", "needs 4")
    assert re.search(r"found [0-3] dwell plateau", err), err


def test_bad_data(example, capsys, tmp_path):
    root, _ = example
    data = root / "data"
    bad = tmp_path / "data"
    bad.mkdir()
    for f in data.iterdir():
        shutil.copy(f, bad / f.name)
    shutil.copy(root / "imu6_bias_start.toml", tmp_path / "imu6_bias_start.toml")
    cfg = tmp_path / "c.toml"
    cfg.write_text((root / "imu6_bias.toml").read_text())
    out = str(tmp_path / "o")
    hold_i, hold_t = bad / "holdout_inertial.csv", bad / "holdout_temperature.csv"
    orig_i, orig_t = hold_i.read_text(), hold_t.read_text()

    # bias column missing
    def drop_accel(lines):
        head = [i for i, s in enumerate(lines) if s.startswith("time_s")][0]
        j = lines[head].split(",").index("accel_x_ug")
        return [",".join(c for k, c in enumerate(s.split(",")) if k != j)
                if i >= head else s for i, s in enumerate(lines)]
    _edit_csv(data / "holdout_inertial.csv", hold_i, drop_accel)
    _fails(capsys, ["calibrate", str(cfg), "--out", out], "holdout_inertial.csv",
           "'accel_x_ug'", "no column")

    # bias column all NaN
    def nan_accel(lines):
        head = [i for i, s in enumerate(lines) if s.startswith("time_s")][0]
        j = lines[head].split(",").index("accel_x_ug")
        return [",".join("nan" if k == j else c for k, c in enumerate(s.split(",")))
                if i > head else s for i, s in enumerate(lines)]
    _edit_csv(data / "holdout_inertial.csv", hold_i, nan_accel)
    _fails(capsys, ["calibrate", str(cfg), "--out", out], "holdout_inertial.csv",
           "'accel_x_ug'", "all NaN")

    # timestamps going backwards (line named)
    def backwards(lines):
        head = [i for i, s in enumerate(lines) if s.startswith("time_s")][0]
        lines[head + 50], lines[head + 51] = lines[head + 51], lines[head + 50]
        return lines
    _edit_csv(data / "holdout_inertial.csv", hold_i, backwards)
    _fails(capsys, ["calibrate", str(cfg), "--out", out], "holdout_inertial.csv", "line",
           "time_s")
    hold_i.write_text(orig_i)

    # no overlapping time: the inertial clock a day later
    def shifted(lines):
        head = [i for i, s in enumerate(lines) if s.startswith("time_s")][0]
        return [(f"{float(s.split(',')[0]) + 86400.0!r}," + s.split(",", 1)[1])
                if i > head else s for i, s in enumerate(lines)]
    _edit_csv(data / "holdout_inertial.csv", hold_i, shifted)
    _fails(capsys, ["calibrate", str(cfg), "--out", out], "holdout_inertial.csv",
           "do not overlap", "time_s")
    hold_i.write_text(orig_i)
    hold_t.write_text(orig_t)

    # one logger glitch in the temperature log: named by line and column before any
    # work (the LinAlgError of issue 32); with outliers.implausible = "drop" it is a
    # dropped sample and the config prepares
    def glitch(lines):
        head = [i for i, s in enumerate(lines) if s.startswith("time_s")][0]
        j = lines[head].split(",").index("T_asic")
        cells = lines[head + 40].split(",")
        cells[j] = "1e300"
        lines[head + 40] = ",".join(cells)
        return lines
    _edit_csv(data / "holdout_temperature.csv", hold_t, glitch)
    _fails(capsys, ["calibrate", str(cfg), "--out", out], "holdout_temperature.csv",
           "'T_asic'", "line")
    from thermojax.calibration._pipeline import prepare

    dropping = tmp_path / "drop.toml"
    dropping.write_text(cfg.read_text().replace("[outliers]\n",
                                                '[outliers]\nimplausible = "drop"\n'))
    with pytest.warns(UserWarning, match="T_asic"):
        prepare(dropping)
    hold_t.write_text(orig_t)
    assert not (tmp_path / "o").exists()  # nothing written on any of these
