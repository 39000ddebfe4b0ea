"""The example files a `pip install` carries (thermojax/data/) are the repository's, and
`calibrate --make-example-data` writes a complete example from them alone."""

from __future__ import annotations

from pathlib import Path

import pytest

from thermojax.calibration._config import load_config
from thermojax.calibration._synthetic import EXAMPLE_FOLDER
from thermojax.cli import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("packaged, repository", [
    ("calibration/imu6_bias_truth.toml", "configs/imu6_bias.toml"),
    ("calibration/imu6_bias.toml", "configs/calibration/imu6_bias.toml"),
    ("calibration/imu6_bias_start.toml", "configs/calibration/imu6_bias_start.toml"),
    ("imu6.toml", "configs/imu6.toml"),
    ("rtd2.toml", "configs/rtd2.toml"),
])
def test_packaged_copies_are_the_repository_files(packaged, repository):
    assert (EXAMPLE_FOLDER.parent / packaged).read_bytes() == (ROOT / repository).read_bytes()


def test_package_data_ships_the_example_folder():
    import tomllib

    with open(ROOT / "pyproject.toml", "rb") as f:
        data = tomllib.load(f)["tool"]["setuptools"]["package-data"]["thermojax"]
    assert "data/calibration/*.toml" in data


@pytest.mark.slow
def test_make_example_data_writes_a_config_that_reads_its_logs(tmp_path, capsys):
    out = tmp_path / "example"
    assert main(["calibrate", "--make-example-data", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert f"thermojax calibrate {out / 'imu6_bias.toml'}" in said
    config = load_config(out / "imu6_bias.toml")
    assert [r.name for r in config.runs] == ["plateaus", "transients", "holdout"]
    assert all(Path(r.temperature).parent == out and Path(r.temperature).is_file()
               for r in config.runs)


def test_make_example_data_takes_the_folder_lock_before_any_work(tmp_path, capsys,
                                                                  monkeypatch):
    """A second writer into the example folder is refused, naming the holder, before a
    single log is simulated (issue 32, item 2)."""
    import os

    import thermojax.calibration._synthetic as synthetic
    from thermojax.cli._outputs import output_lock

    monkeypatch.setattr(synthetic, "synthetic_imu_logs", lambda out: pytest.fail("simulated"))
    out = tmp_path / "example"
    with output_lock(out, "calibrate"):
        rc = main(["calibrate", "--make-example-data", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "another thermojax run" in err and f"pid {os.getpid()}" in err
    assert "Traceback" not in err and not out.exists()
