"""Issue 67, items 6 and 7: configs reject unknown keys and keep outputs inside `--out`,
expressions refuse what would crash or hang, sizes are checked before work, and a damaged
compile-cache entry is removed and recompiled with a warning. Each refusal is exit 2 with
a message naming the file and the field, never a traceback."""

from __future__ import annotations

import pickle
import shutil
import warnings

import numpy as np
import pytest

from thermojax.cli import main

from helpers import CONFIGS, ROOT
from helpers import run_cli as run, assert_refused as refused

RTD2 = CONFIGS / "rtd2.toml"


@pytest.fixture(scope="module")
def shock_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "shock.csv"
    assert main(["simulate", "--model", str(RTD2), "--profile", "shock", "--out", str(path),
                 "--noise", "--quiet"]) == 0
    return path


# ---------------------------------------------------------------------------
# item 6: configs and paths


def _run_config(tmp_path, text):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(f'model = "{RTD2}"\nout = "{tmp_path / "results"}"\n' + text)
    return cfg


@pytest.mark.parametrize("text, field", [
    ('[synthetic]\ntruth = "{m}"\nprofiles = ["shock"]\ndtt = 2.0\n', "synthetic.dtt"),
    ('[synthetic]\ntruth = "{m}"\nprofiles = ["shock"]\nseed = -1\n', "synthetic.seed"),
    ('name = "../../../escape"\ndata = ["{d}"]\n', "name"),
    ('name = "a/b"\ndata = ["{d}"]\n', "name"),
    ('data = ["{d}"]\n[options]\nperturb = -5\n', "options.perturb"),
    ('data = ["{d}"]\n[options]\nstarts = 0\n', "options.starts"),
])
def test_run_config_mistakes_are_refused_before_work(capsys, tmp_path, shock_csv, text, field):
    cfg = _run_config(tmp_path, text.format(m=RTD2, d=shock_csv))
    rc, _, err = run(capsys, "run", cfg, "--quiet")
    refused(rc, err, str(cfg), f"field '{field}'")
    assert not (tmp_path / "results").exists()
    assert not (tmp_path.parent.parent / "escape").exists()


def test_calibrate_rejects_an_unknown_outliers_key(capsys, tmp_path):
    cal = tmp_path / "cal"
    (cal / "data").mkdir(parents=True)
    for name in ("imu6_bias.toml", "imu6_bias_start.toml"):
        shutil.copy(CONFIGS / "calibration" / name, cal / name)
    for run_name in ("plateaus", "transients", "holdout"):
        for kind in ("temperature", "inertial"):
            (cal / "data" / f"{run_name}_{kind}.csv").write_text("")
    cfg = cal / "imu6_bias.toml"
    cfg.write_text(cfg.read_text().replace("n_sigmas = 3.0", "n_sigmas = 3.0\nwindw = 9"))
    rc, _, err = run(capsys, "calibrate", cfg, "--out", tmp_path / "res")
    refused(rc, err, "field 'outliers.windw'")


@pytest.mark.parametrize("name", ["", "..", "x" * 300])
def test_fit_refuses_unusable_out_folders(capsys, tmp_path, monkeypatch, shock_csv, name):
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", name)
    refused(rc, err, "--out")


def test_fit_refuses_a_dangling_symlink_as_out(capsys, tmp_path, shock_csv):
    link = tmp_path / "res"
    link.symlink_to(tmp_path / "gone" / "res")
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", link)
    refused(rc, err, "--out", "symbolic link")


EXPRESSION = """
[[effects]]
kind = "expression"
where = ["core"]
expression = "{e}"
parameters = {{ h = 0.01 }}
"""


@pytest.mark.parametrize("expression, needle", [
    ("(" * 5000 + "h * (T_fluid - core)" + ")" * 5000, "expression"),
    ("(" * 100 + "h * (T_fluid - core)" + ")" * 100, "nests deeper"),
    ("h * (T_fluid - core) / 0", "divides by zero"),
    ("h * (T_fluid - core) / (2 - 2)", "divides by zero"),
    ("h * log(0) * (T_fluid - core)", "not finite"),
])
def test_expressions_that_cannot_be_evaluated_are_refused(capsys, tmp_path, shock_csv,
                                                          expression, needle):
    model = tmp_path / "m.toml"
    model.write_text(RTD2.read_text() + EXPRESSION.format(e=expression))
    rc, _, err = run(capsys, "fit", "--model", model, "--data", shock_csv, "--out",
                     tmp_path / "fit")
    refused(rc, err, "effects[0].expression", needle)


def test_an_unknown_expression_name_is_named(capsys, tmp_path, shock_csv):
    model = tmp_path / "m.toml"
    model.write_text(RTD2.read_text() + EXPRESSION.format(e="h * (T_flud - core)"))
    rc, _, err = run(capsys, "fit", "--model", model, "--data", shock_csv, "--out",
                     tmp_path / "fit")
    refused(rc, err, "T_flud")
    rc, _, err = run(capsys, "simulate", "--model", model, "--profile", "shock", "--out",
                     tmp_path / "s.csv")
    refused(rc, err, "T_flud")


# ---------------------------------------------------------------------------
# item 7: sizes and the cache


def test_montecarlo_refuses_a_billion_units_with_the_predicted_memory(capsys, tmp_path):
    cfg = tmp_path / "mc.toml"
    text = (CONFIGS / "montecarlo" / "imu6_oem.toml").read_text()
    text = text.replace("n_units = 256", "n_units = 1000000000").replace(
        'model = "../imu6_bias.toml"', f'model = "{CONFIGS / "imu6_bias.toml"}"')
    cfg.write_text(text)
    rc, _, err = run(capsys, "montecarlo", str(cfg), "--out", tmp_path / "mc")
    refused(rc, err, "field 'n_units'", "GB", "memory")
    assert not (tmp_path / "mc").exists()


def test_fit_refuses_dev_zero(capsys, tmp_path):
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", "/dev/zero", "--out",
                     tmp_path / "f")
    refused(rc, err, "/dev/zero", "NUL")


def test_a_file_over_the_byte_budget_is_refused_before_reading(tmp_path, monkeypatch):
    from thermojax._errors import InputError
    from thermojax.measurements import _file_size
    from thermojax.measurements import read_telemetry

    path = tmp_path / "big.csv"
    path.write_text("time_s,T_fluid,T_core\n" + "".join(f"{i},25,25\n" for i in range(1000)))
    monkeypatch.setattr(_file_size, "byte_limit", lambda: 1000)
    with pytest.raises(InputError, match="memory"):
        read_telemetry(path)
    monkeypatch.setattr(_file_size, "byte_limit", lambda: 10 ** 9)
    assert len(read_telemetry(path).ts) == 1000


def test_a_damaged_cache_entry_is_removed_and_recompiled(tmp_path, monkeypatch):
    """The traced-program cache: an entry whose content hash fails, one that does not
    unpickle, and an old-format entry (no hash) whose program does not compile are each
    removed with a warning, and the program runs."""
    import jax.numpy as jnp

    from thermojax.compilation import _traced_cache as tc

    monkeypatch.setattr(tc, "_folder", lambda: tmp_path / "traced")

    @tc.stored_jit
    def f(x):
        return jnp.sin(x) * 2.0

    x = jnp.arange(4.0)
    want = np.asarray(f(x))
    (entry,) = list((tmp_path / "traced").iterdir())
    good = entry.read_bytes()

    def damage(kind):
        blob = pickle.loads(good)
        b = bytearray(blob["exported"])
        b[len(b) // 3: len(b) // 3 + 64] = bytes(64)
        blob["exported"] = bytes(b)
        if kind == "old":
            del blob["sha256"]
        entry.write_bytes(b"garbage" if kind == "garbage" else pickle.dumps(blob))

    for kind in ("hash", "garbage", "old"):
        tc.forget_programs()
        damage(kind)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            got = np.asarray(f(x))
        np.testing.assert_array_equal(got, want)
        assert any("compile-cache entry" in str(w.message) for w in caught), kind
        tc.forget_programs()
        with warnings.catch_warnings(record=True) as caught:  # stored afresh: no warning
            warnings.simplefilter("always")
            np.testing.assert_array_equal(np.asarray(f(x)), want)
        assert not any("compile-cache entry" in str(w.message) for w in caught), kind
        good = entry.read_bytes()


def test_a_damaged_jax_cache_entry_is_removed_and_recompiled(tmp_path):
    """JAX's own persistent cache (the command line's default): a damaged entry is
    removed with a warning and stored afresh, so the next run is quiet."""
    import os
    import subprocess
    import sys

    script = (
        "import sys, jax, jax.numpy as jnp\n"
        "from thermojax.compilation._cache import enable_compilation_cache\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "enable_compilation_cache(sys.argv[1])\n"
        "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.0)\n"
        "f = jax.jit(lambda x: jnp.linalg.solve(x @ x.T + jnp.eye(8), jnp.sin(x).sum(1)))\n"
        "print(float(f(jnp.arange(64.0).reshape(8, 8) / 64).sum()))\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))

    def run_once():
        return subprocess.run([sys.executable, "-c", script, str(tmp_path / "cache")],
                              env=env, capture_output=True, text=True, timeout=300)

    first = run_once()
    assert first.returncode == 0, first.stderr
    entries = list((tmp_path / "cache").rglob("*-cache"))
    assert entries
    for e in entries:
        data = bytearray(e.read_bytes())
        data[len(data) // 2: len(data) // 2 + 64] = bytes(64)
        e.write_bytes(bytes(data))
    again = run_once()
    assert again.returncode == 0 and again.stdout == first.stdout, again.stderr
    assert "compile-cache entry" in again.stderr and "Traceback" not in again.stderr
    quiet = run_once()
    assert quiet.returncode == 0 and "compile-cache entry" not in quiet.stderr
    assert quiet.stdout == first.stdout
