"""`thermojax compensate` (spec §5): the fluid temperature a lagging RTD sees, from its
readings alone. The truth is the fluid temperature the test generated; the readings come
from `scipy.signal.lsim` of the model's matrices (read with tomllib, no thermojax)."""

from __future__ import annotations

import numpy as np
import scipy.signal

import thermojax as tj
from thermojax.cli import main

from helpers import CONFIGS, model_matrices

DT = 0.1


def _log(tmp_path, seconds=600.0, seed=0):
    """A fluid stepping between random levels every 60 s (each step over one sample),
    the core sensor's reading with 0.01 °C noise, written as a telemetry CSV."""
    rng = np.random.default_rng(seed)
    ts = DT * np.arange(int(seconds / DT) + 1)
    levels = rng.uniform(20.0, 100.0, int(seconds // 60) + 1)
    fluid = levels[(ts // 60).astype(int)]
    m = model_matrices(CONFIGS / "rtd2.toml")
    x0 = np.linalg.solve(m["A"], -m["B"][:, 0] * fluid[0])
    _, y, _ = scipy.signal.lsim((m["A"], m["B"], m["Cy"], np.zeros((1, 1))), fluid, ts,
                                X0=x0, interp=True)
    reading = np.asarray(y).reshape(-1) + 0.01 * rng.standard_normal(ts.size)
    path = tmp_path / "log.csv"
    tj.write_telemetry(path, ts, {"T_core": reading})
    return path, ts, fluid, reading


def test_compensate_recovers_the_fluid_far_faster_than_the_sensor(tmp_path, capsys):
    path, ts, fluid, reading = _log(tmp_path)
    out = tmp_path / "fluid.csv"
    assert main(["compensate", "--model", str(CONFIGS / "rtd2.toml"), "--data", str(path),
                 "--input", "T_fluid", "--out", str(out), "--quiet"]) == 0
    assert "maximum likelihood" in capsys.readouterr().out
    got = tj.read_telemetry(out)
    assert list(got.names) == ["T_fluid", "T_fluid_std", "T_fluid_settled"]
    np.testing.assert_array_equal(got.ts, ts)
    est, std = np.asarray(got.column("T_fluid")), np.asarray(got.column("T_fluid_std"))
    settled = ts > 5.0
    raw_err = np.sqrt(np.mean((reading - fluid)[settled] ** 2))
    err = np.sqrt(np.mean((est - fluid)[settled] ** 2))
    assert err < raw_err / 3, (err, raw_err)
    # between steps (10 s after one) the reconstruction sits within its 3-std band
    calm = (ts % 60 > 10.0) & settled
    assert np.mean(np.abs(est - fluid)[calm] <= 3 * std[calm]) > 0.95
    assert out.with_suffix(".png").stat().st_size > 10_000  # sensor, estimate and band
    # written by thermojax: a second run may replace it
    assert main(["compensate", "--model", str(CONFIGS / "rtd2.toml"), "--data", str(path),
                 "--input", "T_fluid", "--out", str(out), "--input-noise", "0.5",
                 "--quiet"]) == 0


def test_compensate_mistakes_are_named(tmp_path, capsys):
    path, ts, fluid, reading = _log(tmp_path, seconds=60.0)
    model = str(CONFIGS / "rtd2.toml")

    def run(*extra, out="f.csv"):
        code = main(["compensate", "--model", model, "--data", str(path),
                     "--out", str(tmp_path / out), "--quiet", *extra])
        return code, capsys.readouterr().err

    code, err = run("--input", "T_air")
    assert code == 2 and "--input" in err and "T_fluid" in err
    (tmp_path / "mine.csv").write_text("a,b\n1,2\n")
    code, err = run("--input", "T_fluid", out="mine.csv")
    assert code == 2 and "--force" in err
    uneven = tmp_path / "uneven.csv"
    tj.write_telemetry(uneven, np.r_[ts[:10], ts[11:]], {"T_core": np.r_[reading[:10],
                                                                         reading[11:]]})
    code = main(["compensate", "--model", model, "--data", str(uneven), "--input",
                 "T_fluid", "--out", str(tmp_path / "g.csv"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "resample" in err and "line 12" in err
    glitched = tmp_path / "glitch.csv"  # a logger glitch: refused by line, never absorbed
    tj.write_telemetry(glitched, ts, {"T_core": np.where(np.arange(ts.size) == 40, 1e300,
                                                          reading)})
    code = main(["compensate", "--model", model, "--data", str(glitched), "--input",
                 "T_fluid", "--out", str(tmp_path / "k.csv"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "line 42" in err and "'T_core'" in err and "every sample" in err
    assert "--outliers" not in err  # compensate has no such option
    nonlinear = tmp_path / "rad.toml"
    nonlinear.write_text((CONFIGS / "rtd2.toml").read_text() + '\n[[effects]]\nkind = '
                         '"radiation"\nwhere = ["sheath", "T_fluid"]\ncoefficient = 1e-10\n')
    code = main(["compensate", "--model", str(nonlinear), "--data", str(path), "--input",
                 "T_fluid", "--out", str(tmp_path / "h.csv"), "--quiet"])
    assert code == 2 and "radiation" in capsys.readouterr().err
