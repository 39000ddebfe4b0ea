"""The unit-variance Monte Carlo stage (issue 14): populations, the chunk store and its
resume, sharding over devices and processes, the command line."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

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
    assert report["n_units"] == 20 and set(report["methods"]) == {"nominal", "own"}
    assert 0 <= report["fraction_within_bias_spec"]["nominal"] <= 1
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
            # differences the errors are (hence an absolute 1e-12, not a relative bound)
            np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=1e-12, err_msg=key)


def test_two_processes_share_the_chunks_then_merge(reference, env):
    folder, cfg, ref = reference
    out = folder / "two"
    procs = [subprocess.Popen([sys.executable, "-m", "thermojax", "montecarlo", str(cfg),
                               "--out", str(out), "--quiet", "--resume"], cwd=ROOT,
                              env={**env, "THERMOJAX_PROCESS_INDEX": str(i),
                                   "THERMOJAX_PROCESS_COUNT": "2"},
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    merged = cli([str(cfg), "--out", str(out), "--resume"], env)
    assert main_ok(merged) and "0 chunk(s) computed, 4 resumed" in merged.stdout
    assert chunk_bytes(out) == chunk_bytes(ref)
    assert (out / "report.json").is_file()
