"""The unit-variance Monte Carlo stage (issue 14): populations, the chunk store and its
resume, sharding over devices and processes, the command line.

The chunk store's fits are made on data from `Study.calibration_data`, the simulation the
fit itself uses, so the checks on them are consistency checks. Recovery of a unit's
parameters is checked on calibration data made outside thermojax: `scipy_calibration_data`
simulates a unit with the tests' `chamber_truth` (tomllib, `scipy.linalg.expm`, NumPy bias
terms) and NumPy noise, and the fit must find the parameters that unit was made with."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import tomllib

import numpy as np
import pytest

from chamber_truth import observe, read_chamber_model, simulate

import thermojax as tj
from thermojax.cli._main import main
from thermojax.montecarlo import (PRESETS, chunks_of_process, kalman_gain_doubling,
                                  population_from_config, preset_population, sample_units)

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "configs" / "imu6_bias.toml"

CONFIG = """
model = "{model}"
n_units = 20
chunk_size = 6
seed = {seed}

[population]
preset = "bare_die_custom"
[[population.groups]]
parameters = ["links.pcb-asic.conductance", "links.pcb-mems.conductance"]
correlation = 0.5
[[population.voids]]
link = "pcb-asic"
probability = 0.3
max_loss = 0.5

[profile]
lo = 0.0
hi = 40.0
rate = 20.0
dwell = 30.0
dt = 2.0
power = 0.05

[spec]
bias_limit = 0.5
"""


def scipy_calibration_data(study, logdev, seed: int):
    """A unit's calibration readings `(times, sensors)` and bias column `(times,)` made
    outside thermojax: configs/imu6_bias.toml read with `tomllib`, each varied parameter
    multiplied by `exp(logdev[j])` (a log-deviation), simulated by `chamber_truth` (exact
    for the chamber temperature linear and the power held between samples) through the
    study's calibration inputs, plus NumPy white noise of each column's std."""
    doc = tomllib.loads(MODEL.read_text())
    entries = {"nodes": {n["name"]: n for n in doc["nodes"]},
               "links": {"-".join(k["between"]): k for k in doc["links"]},
               "boundaries": {f"{b['node']}-{b['input']}": b for b in doc["boundaries"]},
               "heat_inputs": {f"{h['node']}-{h['input']}": h for h in doc["heat_inputs"]}}
    for name, d in zip(study.names, np.asarray(logdev, float)):
        group, rest = name.split(".", 1)
        key, field = rest.rsplit(".", 1)
        entry = entries[group][key]
        v = entry[field]
        entry[field] = ({**v, "value": v["value"] * np.exp(d)} if isinstance(v, dict)
                        else v * np.exp(d))
    model = read_chamber_model(doc)
    columns = list(study.network.topology.input_names)
    U = np.asarray(study.inputs_cal)[:, [columns.index(c) for c in model.inputs]]
    clean = observe(model, simulate(model, study.ts_cal, U), U)
    rng = np.random.default_rng(seed)
    sensors = list(model.sensors)
    y = np.column_stack([clean[c] for c in sensors])
    y = y + np.asarray(study.noise)[None, :] * rng.standard_normal(y.shape)
    b = clean[study.bias.column] + study.bias_noise * rng.standard_normal(y.shape[0])
    return y, b


@pytest.fixture(scope="module")
def spec():
    return tj.load_model(MODEL)


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """Subprocess environment: one compilation cache for the module's runs."""
    e = dict(os.environ)
    e["THERMOJAX_CACHE_DIR"] = str(tmp_path_factory.mktemp("cache"))
    e.pop("XLA_FLAGS", None)
    for k in ("THERMOJAX_PROCESS_INDEX", "THERMOJAX_PROCESS_COUNT", "THERMOJAX_MONTECARLO_PAUSE"):
        e.pop(k, None)
    return e


def write_config(folder: Path, seed: int = 0, text: str = CONFIG) -> Path:
    path = folder / f"mc_seed{seed}.toml"
    path.write_text(text.replace("{model}", str(MODEL)).replace("{seed}", str(seed)))
    return path


def cli(args, env, extra=None, **kw):
    return subprocess.run([sys.executable, "-m", "thermojax", "montecarlo", *args, "--quiet"],
                          env={**env, **(extra or {})}, capture_output=True, text=True,
                          cwd=ROOT, timeout=300, **kw)


def chunk_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((folder / "chunks").glob("chunk_*.npz"))}


# -- populations -------------------------------------------------------------------------

def test_lognormal_spread_and_correlation_recovered(spec):
    a, b = "links.pcb-asic.conductance", "nodes.mems.capacitance"
    pop = population_from_config(spec, {"spreads": {a: 0.2, b: 0.3},
                                        "groups": [{"parameters": [a, b], "correlation": 0.7}]})
    units = sample_units(spec, pop, 4000, seed=3)
    nominal = units.values[0] / np.exp(units.log_deviation[0])
    ratio = units.values / nominal
    # 4000 draws: standard errors about 0.2/sqrt(2*4000) ~ 0.003 on a std, 0.006 on a mean
    np.testing.assert_allclose(ratio.mean(axis=0), [1.0, 1.0], atol=0.02)
    np.testing.assert_allclose(ratio.std(axis=0), [0.2, 0.3], rtol=0.08)
    assert np.all(units.values > 0)
    r = np.corrcoef(units.log_deviation.T)[0, 1]
    assert abs(r - 0.7) < 0.04  # standard error of r about (1 - 0.49)/sqrt(4000) ~ 0.008
    # deterministic by (seed, unit): a subset drawn alone equals those rows of the whole
    again = sample_units(spec, pop, [17, 3999, 5], seed=3)
    np.testing.assert_array_equal(again.values, units.values[[17, 3999, 5]])


def test_presets_touch_the_stated_parameters(spec):
    from thermojax.model import spec_parameters

    names = list(spec_parameters(spec))
    stated = [n for n in names if (n.startswith("nodes.") and n.endswith(".capacitance"))
              or (n.startswith("links.") and n.endswith(".conductance"))]
    for preset, entry in PRESETS.items():
        pop = preset_population(spec, preset)
        assert list(pop.spreads) == stated
        assert set(pop.spreads.values()) == {entry["spread"]}
    assert {k: v["spread"] for k, v in PRESETS.items()} == {
        "asic_integrated": 0.05, "oem_module": 0.12, "bare_die_custom": 0.18,
        "thermistor_custom_housing": 0.32}


def test_voids_lose_conductance_on_the_named_link(spec):
    pop = population_from_config(spec, {"voids": [{"link": "pcb-asic", "probability": 1.0,
                                                   "max_loss": 0.5}]})
    units = sample_units(spec, pop, 500, seed=0)
    ratio = np.exp(units.log_deviation[:, 0])
    assert units.names == ("links.pcb-asic.conductance",)
    assert ratio.min() >= 0.5 and ratio.max() <= 1.0 and abs(ratio.mean() - 0.75) < 0.03


def test_doubling_gain_equals_scipy_riccati(spec):
    from thermojax.montecarlo import Study

    study = Study(spec, (), {"lo": 0, "hi": 40, "rate": 20, "dwell": 30, "dt": 2.0})
    _, _, gain = study.observer_of(study.network)
    ref = tj.design_observer(study.network, 2.0).gain
    # both solve the same DARE; float64 roundoff only
    np.testing.assert_allclose(np.asarray(gain), np.asarray(ref), rtol=1e-9, atol=1e-12)


def test_chunk_assignment_is_a_partition():
    shares = [chunks_of_process(11, i, 3) for i in range(3)]
    assert sorted(sum(shares, [])) == list(range(11))
    assert all(set(a).isdisjoint(b) for i, a in enumerate(shares) for b in shares[i + 1:])


# -- bad input ---------------------------------------------------------------------------

@pytest.mark.parametrize("population, field, words", [
    ('spreads = { "links.pcb-asic.conductance" = -0.1 }',
     "population.spreads.links.pcb-asic.conductance", "cannot be negative"),
    ('spreads = { "links.pcb-asic.conductance" = "lots" }',
     "population.spreads.links.pcb-asic.conductance", "expected a finite number"),
    ('preset = "gold_plated"', "population.preset", "unknown preset"),
    ('spreads = { "links.pcb-nowhere.conductance" = 0.1 }',
     "population.spreads.links.pcb-nowhere.conductance", "has no parameter"),
])
def test_bad_population_exits_2_naming_the_field(tmp_path, capsys, population, field, words):
    head, rest = CONFIG.split("[population]")
    text = head + "[population]\n" + population + "\n\n[profile]" + rest.split("[profile]")[1]
    cfg = write_config(tmp_path, text=text)
    assert main(["montecarlo", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"field '{field}'" in err and words in err and "Traceback" not in err


# -- chunks: resume, corruption, another config, devices, processes -----------------------

@pytest.fixture(scope="module")
def reference(tmp_path_factory, env):
    """An uninterrupted run on one device."""
    folder = tmp_path_factory.mktemp("mc")
    cfg = write_config(folder)
    got = cli([str(cfg), "--out", str(folder / "ref")], env)
    assert got.returncode == 0, got.stderr
    return folder, cfg, folder / "ref"


def test_report_and_plots(reference):
    _, _, ref = reference
    report = json.loads((ref / "report.json").read_text())
    assert report["n_units"] == 20 and set(report["methods"]) == {"nominal", "fitted", "own"}
    # the fractions within the bias spec, recounted here from the chunks' per-unit peaks
    # and the config's limit (0.5): exact multiples of 1/20
    r = load_chunks(ref)
    for m in report["methods"]:
        want = np.count_nonzero(r[f"{m}_bias_peak"] <= 0.5) / 20
        assert report["fraction_within_bias_spec"][m] == want, (m, want)
    assert report["sensitivity"][0]["parameter"].startswith(("links.", "nodes."))
    from PIL import Image

    for name in ("bias_peak_distribution.png", "temp_peak_distribution.png"):
        with Image.open(ref / name) as image:
            assert image.size[0] >= 1000
    assert len(chunk_bytes(ref)) == 4


def test_killed_run_resumes_bitwise_identical(reference, env):
    folder, cfg, ref = reference
    out = folder / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "thermojax", "montecarlo", str(cfg), "--out",
                             str(out), "--quiet"], cwd=ROOT,
                            env={**env, "THERMOJAX_MONTECARLO_PAUSE": "3"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while not (out / "chunks" / "chunk_00000.json").exists():
        assert proc.poll() is None and time.time() < deadline, "no chunk was written"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 1 <= len(chunk_bytes(out)) < 4 and not (out / "report.json").exists()
    again = cli([str(cfg), "--out", str(out), "--resume"], env)
    assert main_ok(again)
    assert "resumed" in again.stdout
    assert chunk_bytes(out) == chunk_bytes(ref)
    # a corrupt chunk is detected and computed again, never mixed in
    bad = out / "chunks" / "chunk_00002.npz"
    bad.write_bytes(bad.read_bytes()[:100])
    again = cli([str(cfg), "--out", str(out), "--resume"], env)
    assert main_ok(again) and "1 chunk(s) computed, 3 resumed" in again.stdout
    assert chunk_bytes(out) == chunk_bytes(ref)
    # without --resume (or --force) an earlier run's folder is refused
    assert cli([str(cfg), "--out", str(out)], env).returncode == 2
    # a different config's folder is refused, saying why
    other = write_config(folder, seed=1)
    refused = cli([str(other), "--out", str(out), "--resume"], env)
    assert refused.returncode == 2
    assert "different config" in refused.stderr and "seed" in refused.stderr


def load_chunks(folder: Path) -> dict[str, np.ndarray]:
    parts = [np.load(p) for p in sorted((folder / "chunks").glob("chunk_*.npz"))]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0].files}


def test_fitted_units_approach_their_own_model(reference, spec):
    """Consistency check of the chunk store: each unit's fit against the parameters the
    sampler drew for it. The data come from `Study.calibration_data`, the simulation the
    fit itself uses, so an error shared by both would cancel here; recovery on data made
    outside thermojax is `test_fit_recovers_units_simulated_by_scipy`."""
    _, _, ref = reference
    r = load_chunks(ref)
    names = list(json.loads((ref / "report.json").read_text())["population"]["spreads"])
    nominal, fitted, own = (np.median(r[f"{m}_bias_peak"]) for m in ("nominal", "fitted", "own"))
    # identification closes most of the gap between nominal and the true-model bound
    assert abs(fitted - own) < 0.1 * abs(nominal - own)
    assert np.median(r["fitted_temp_peak"]) < 0.1 * np.median(r["nominal_temp_peak"])
    # the calibration residuals are at the noise level (in noise stds)
    np.testing.assert_allclose(np.median(r["fit_rms"]), 1.0, atol=0.1)
    for name in ("nodes.housing.capacitance", "links.bulkhead-pcb.conductance",
                 "links.pcb-asic.conductance"):
        j = names.index(name)
        err = r["fitted_log_deviation"][:, j] - r["log_deviation"][:, j]
        std = r["fitted_log_std"][:, j]
        # identifiable: the posterior std is far below the population's 18 % spread, and
        # every unit's estimate lies within 4 posterior stds of its true value
        assert np.all(std < 0.05), name
        assert np.all(np.abs(err) < 4 * std), (name, err / std)


@pytest.fixture(scope="module")
def one_unit(reference):
    """The reference config's study, and one unit's fit by itself (jitted, not vmapped)."""
    import jax
    import jax.numpy as jnp

    from thermojax.montecarlo import load_config, study_of

    _, cfg, ref = reference
    study = study_of(load_config(cfg))
    data = jax.jit(study.calibration_data)
    fit = jax.jit(study.fit)
    fit_one = lambda d, u: fit(*data(jnp.asarray(d), u, 0))  # noqa: E731
    fit_one.fit = fit  # the jitted fit alone, for data made elsewhere
    return study, fit_one


def test_fit_recovers_units_simulated_by_scipy(reference, one_unit):
    """Three units of the reference population (the sampler's draws, incl. voids)
    simulated outside thermojax (`scipy_calibration_data`), fitted by the study's fit:
    each identifiable parameter (posterior std < 0.05) within 4 posterior stds of the
    value the unit was made with, and the residuals at the noise level, as the chunk
    store's consistency check asks of its own data."""
    _, _, ref = reference
    r = load_chunks(ref)
    study, fit_one = one_unit
    assert list(read_chamber_model(MODEL).sensors) == list(
        study.network.topology.sensor_names)
    for u in (0, 1, 2):
        made = r["log_deviation"][u]
        y, b = scipy_calibration_data(study, made, seed=100 + u)
        d, std, rms = map(np.asarray, fit_one.fit(y, b))
        np.testing.assert_allclose(rms, 1.0, atol=0.1)
        ident = std < 0.05
        assert ident.sum() >= 6, std
        assert np.all(np.abs(d - made)[ident] < 4 * std[ident]), (u, (d - made) / std)


def test_batched_fit_equals_one_unit_fit(reference, one_unit):
    """The vmapped chunk program's fit of one unit against that unit fitted alone."""
    _, _, ref = reference
    r = load_chunks(ref)
    study, fit_one = one_unit
    u = 7
    d, std, rms = fit_one(r["log_deviation"][u], u)
    # the same arithmetic unbatched, in another process: the data agree to 1e-13 °C; the
    # minimum (polished by Gauss-Newton steps) to roundoff amplified by the Hessian's
    # conditioning, about 1e-11 in the log-parameters (posterior stds 0.005 to 0.2)
    np.testing.assert_allclose(np.asarray(d), r["fitted_log_deviation"][u], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(std), r["fitted_log_std"][u], rtol=1e-9)
    # the residual RMS is taken one polish step before the estimate: that point agrees
    # to the same roundoff, and the RMS (stationary there) to about 1e-12
    np.testing.assert_allclose(float(rms), r["fit_rms"][u], rtol=1e-10)


@pytest.mark.slow
def test_batch_model_of_copies_of_one_unit_recovers_it(reference, one_unit):
    """Consistency check: the pooled (batch-level) fit over units that share one
    parameter set, each with its own noise from `Study.calibration_data` (the fit's own
    simulation), returns that set."""
    _, _, ref = reference
    r = load_chunks(ref)
    study, fit_one = one_unit
    shared = r["log_deviation"][3]
    std = np.asarray(fit_one(shared, 100)[1])  # one unit's posterior std; pooled about half
    got = study.set_batch_model(np.repeat(shared[None], 4, axis=0), np.arange(100, 104), 0)
    ident = std < 0.05
    assert ident.sum() >= 6
    assert np.all(np.abs(got - shared)[ident] < 4 * std[ident]), (got - shared) / std
    assert set(study.methods) == {"nominal", "batch", "fitted", "own"}
    study.batch_logdev = None  # the fixture's study is shared


@pytest.mark.parametrize("table, field", [
    ("[fit]\niterations = 0", "fit.iterations"),
    ("[fit]\nbias_column = 3", "fit.bias_column"),
    ("[calibration]\nlo = 0.0\nhi = 40.0\nrate = 20.0\ndwell = 30.0\ndt = -1.0",
     "calibration.dt"),
    ("[calibration]\nlo = 50.0\nhi = 40.0\nrate = 20.0\ndwell = 30.0\ndt = 1.0",
     "calibration.lo"),
])
def test_bad_fit_or_calibration_exits_2_naming_the_field(tmp_path, capsys, table, field):
    cfg = write_config(tmp_path, text=CONFIG + "\n" + table + "\n")
    assert main(["montecarlo", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"field '{field}'" in err and "Traceback" not in err


def main_ok(result) -> bool:
    assert result.returncode == 0, result.stderr
    return True


def test_four_host_devices_equal_one(reference, env):
    folder, cfg, ref = reference
    out = folder / "four"
    got = cli([str(cfg), "--out", str(out)], env,
              {"XLA_FLAGS": "--xla_force_host_platform_device_count=4"})
    assert main_ok(got)
    for name in chunk_bytes(ref):
        a, b = np.load(ref / "chunks" / name), np.load(out / "chunks" / name)
        for key in a.files:
            # the same per-unit program on each device's slice, compiled for another batch
            # size: float64 roundoff, relative to the ~1 deg/h and ~50 °C quantities whose
            # differences the errors are (hence an absolute 1e-12, not a relative bound);
            if key == "fitted_log_deviation":
                # a fit that has not converged to machine precision in its fixed
                # iterations (a unit deep in a void) stops where roundoff takes it, but
                # within a millionth of its posterior std
                z = (b[key] - a[key]) / a["fitted_log_std"]
                assert np.abs(z).max() < 1e-6, np.abs(z).max()
                continue
            # fitted metrics: those stopping points' effect on ~0.01 deg/h errors
            tol = 1e-9 if key.startswith(("fit", "fitted")) else 1e-12
            np.testing.assert_allclose(b[key], a[key], rtol=tol, atol=tol, err_msg=key)


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("launch", ["environment", "jax.distributed"])
def test_two_processes_share_the_chunks_then_merge(reference, env, launch):
    """Two processes on this machine, each computing its share of the chunks into one
    folder: told their share by THERMOJAX_PROCESS_INDEX/COUNT, or through a real
    `jax.distributed` cluster (a coordinator on localhost, as on two hosts)."""
    folder, cfg, ref = reference
    out = folder / f"two_{launch.replace('.', '_')}"
    port = free_port()

    def share(i):
        if launch == "environment":
            return {"THERMOJAX_PROCESS_INDEX": str(i), "THERMOJAX_PROCESS_COUNT": "2"}
        return {"THERMOJAX_DISTRIBUTED": "1", "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}",
                "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": str(i)}

    procs = [subprocess.Popen([sys.executable, "-m", "thermojax", "montecarlo", str(cfg),
                               "--out", str(out), "--quiet", "--resume"], cwd=ROOT,
                              env={**env, **share(i)},
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (stdout, err) in zip(procs, outs):
        assert p.returncode == 0, err
    # each process computed its own two chunks (c mod 2 = its index)
    assert all("2 chunk(s)" in o for o, _ in outs), outs
    merged = cli([str(cfg), "--out", str(out), "--resume"], env)
    assert main_ok(merged) and "0 chunk(s) computed, 4 resumed" in merged.stdout
    assert chunk_bytes(out) == chunk_bytes(ref)
    assert (out / "report.json").is_file()


@pytest.mark.parametrize("fit_bias", [False, True])
def test_fit_jacobian_equals_jacfwd(spec, fit_bias):
    """The fit's forward-sensitivity residuals and Jacobian (`Study._fit_evaluate`)
    against `jax.jacfwd` of the study's own simulation residuals (`Study._residuals`:
    `ExactHold`'s blocked hold and the bias channel on every node), at a unit away from
    the nominal model, with and without the bias column; and the fit runs on both."""
    import jax
    import jax.numpy as jnp

    from thermojax.montecarlo import Study, log_prior, varied_names

    pop = preset_population(spec, "bare_die_custom")
    profile = {"lo": 10.0, "hi": 40.0, "rate": 20.0, "dwell": 60.0, "dt": 2.0, "power": 0.05}
    study = Study(spec, varied_names(pop), profile, prior=log_prior(pop), fit_bias=fit_bias)
    assert study.fit_bias == fit_bias
    k = len(study.names)
    unit = jnp.asarray(np.linspace(-0.2, 0.25, k))
    y, b = jax.jit(study.calibration_data)(unit, 3, 0)
    d = unit + 0.05 * jnp.cos(jnp.arange(k))

    def reference(d):
        r, r_prior = study._residuals(d, y, b)
        return jnp.concatenate([r, r_prior])

    def ours(d):
        r_y, r_b, r_prior, (J_y, J_b) = study._fit_evaluate(d, y[None], b[None])
        bias = (r_b[0],) if fit_bias else ()
        r = jnp.concatenate([r_y[0].ravel(), *bias, r_prior])
        bias = (J_b,) if fit_bias else ()
        J = jnp.concatenate([J_y.reshape(-1, k), *bias, jnp.asarray(study.prior[1])])
        return r, J

    J_ref = np.asarray(jax.jit(jax.jacfwd(reference))(d))
    r_ref = np.asarray(reference(d))
    r, J = map(np.asarray, jax.jit(ours)(d))
    assert J.shape == J_ref.shape == (y.size + (b.size if fit_bias else 0) + k, k)
    # float64 roundoff: residuals of ~10 noise stds from ~30 °C / 0.01 °C readings,
    # Jacobian columns relative to each column's largest entry
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-9)
    scale = np.abs(J_ref).max(axis=0)
    assert np.all(scale > 0)
    err = np.abs(J - J_ref).max(axis=0) / scale
    assert err.max() < 1e-10, err
    got, std, rms = map(np.asarray, jax.jit(study.fit)(y, b))
    assert np.all(np.isfinite(got)) and np.all(std > 0) and abs(float(rms) - 1.0) < 0.15


def test_fit_converges_from_far_and_stops_early(spec):
    """A unit many prior stds from the nominal model, its calibration data simulated
    outside thermojax (`scipy_calibration_data`): the trust-region fit converges (stops
    on its step tolerance well before the cap) to the same estimate from the prior mean
    and from the truth, and that estimate lies within a few posterior stds of the
    truth."""
    import jax
    import jax.numpy as jnp

    from thermojax.montecarlo import Study, log_prior, varied_names

    pop = preset_population(spec, "bare_die_custom")
    profile = {"lo": 0.0, "hi": 40.0, "rate": 20.0, "dwell": 60.0, "dt": 2.0, "power": 0.05}
    study = Study(spec, varied_names(pop), profile, prior=log_prior(pop), iterations=60)
    k = len(study.names)
    truth = jnp.asarray(0.4 * np.sin(np.arange(k) + 1.0))  # up to 2 population stds
    y, b = map(jnp.asarray, scipy_calibration_data(study, np.asarray(truth), seed=5))
    d, std, rms, trials, jacobians = map(np.asarray, jax.jit(
        lambda y, b: study.fit(y, b, steps=True))(y, b))
    # converged on its tolerance, far below the cap of 63 steps (9 Jacobians here)
    assert 1 <= jacobians <= min(20, trials + 1)
    np.testing.assert_allclose(rms, 1.0, atol=0.1)
    ident = std < 0.05
    assert ident.sum() >= 6
    assert np.all(np.abs(d - np.asarray(truth))[ident] < 4 * std[ident])
    # the minimum, not where the iterations happened to stop: from the truth, the same
    d2 = np.asarray(jax.jit(lambda y, b: study.fit(y, b, start=truth))(y, b)[0])
    assert np.abs((d2 - d) / std).max() < 3e-4  # the fit's tolerance: 1e-4 stds


def test_studies_of_one_structure_share_a_program_and_keep_their_own_prior(spec):
    """Two presets (other priors) of one structure: the second study's chunk, computed by
    the program compiled for the first, equals the chunk computed by a program compiled
    for itself alone; a study of another profile gets its own program."""
    from thermojax.montecarlo import Study, log_prior, varied_names
    from thermojax.montecarlo import _study

    profile = {"lo": 0.0, "hi": 40.0, "rate": 20.0, "dwell": 30.0, "dt": 4.0, "power": 0.05}
    pops = [preset_population(spec, p) for p in ("oem_module", "bare_die_custom")]
    studies = [Study(spec, varied_names(p), profile, prior=log_prior(p), iterations=8)
               for p in pops]
    sample = sample_units(spec, pops[1], np.arange(3), seed=1)
    _study._PROGRAMS.clear()
    studies[0].compute_chunk(sample.log_deviation[:2], sample.indices[:2], 1)
    shared = studies[1].compute_chunk(sample.log_deviation, sample.indices, 1)
    assert len(_study._PROGRAMS) == 1  # the second study reused the first's program
    _study._PROGRAMS.clear()
    alone = studies[1].compute_chunk(sample.log_deviation, sample.indices, 1)
    for k in alone:
        np.testing.assert_array_equal(shared[k], alone[k], err_msg=k)
    # the priors differ, so the fits do: the shared program did not keep the first's
    first = studies[0].compute_chunk(sample.log_deviation, sample.indices, 1)
    assert not np.array_equal(first["fitted_log_deviation"], alone["fitted_log_deviation"])
    other = Study(spec, varied_names(pops[1]), dict(profile, rate=10.0),
                  prior=log_prior(pops[1]), iterations=8)
    other.compute_chunk(sample.log_deviation[:1], sample.indices[:1], 1)
    assert len(_study._PROGRAMS) == 2
    _study._PROGRAMS.clear()
