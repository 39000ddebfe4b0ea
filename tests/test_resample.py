"""`resample`: a real logger file (jitter, gaps, dropped cells) onto a uniform grid.

Truth: channels that are linear in time are reproduced exactly by linear
interpolation, and a smooth one within the interpolation bound max|f''| h² / 8."""

import numpy as np
import pytest

from thermojax import InputError
from thermojax.cli import main
from thermojax.measurements import read_telemetry, write_telemetry
from thermojax.measurements._resample import resample

from helpers import CONFIGS


def logger_file(path, rng):
    """1 Hz nominal with ±4 % jitter (over the reader's 1 %), a 20 s gap at 300 s, and
    dropped sensor cells."""
    ts = np.arange(600.0) + rng.uniform(-0.04, 0.04, 600)
    ts[0] = 0.0
    ts = ts[(ts < 300) | (ts > 320)]
    fluid = 20.0 + 0.1 * ts  # linear: interpolation is exact
    core = 50.0 + 10.0 * np.sin(2 * np.pi * ts / 200.0)  # smooth, period 200 s
    core[[50, 400]] = np.nan
    write_telemetry(path, ts, {"T_fluid": fluid, "T_core": core})
    return ts


def bracket_span(ts, t):
    """Distance between the samples on either side of `t` (0 on a sample; inf at an end)."""
    if np.any(ts == t):
        return 0.0
    before, after = ts[ts < t], ts[ts > t]
    return after[0] - before[-1] if before.size and after.size else np.inf


def test_jittery_file_is_refused_by_the_reader(tmp_path):
    path = tmp_path / "log.csv"
    logger_file(path, np.random.default_rng(0))
    with pytest.raises(InputError, match="irregular sampling"):
        read_telemetry(path)


def test_resample_reproduces_known_signals(tmp_path):
    path = tmp_path / "log.csv"
    ts = logger_file(path, np.random.default_rng(0))
    ts_core = np.delete(ts, [50, 400])  # the core's finite samples
    result = resample(read_telemetry(path, uniform=False), 1.0, fill=("T_fluid",))
    grid = np.arange(0.0, result.ts[-1] + 0.5)
    np.testing.assert_array_equal(result.ts, grid)  # k · dt from ts[0] = 0
    # linear channel, filled across the gap: exact up to float64 roundoff
    np.testing.assert_allclose(result.channels["T_fluid"], 20.0 + 0.1 * grid, rtol=0,
                               atol=1e-12)
    core = result.channels["T_core"]
    in_gap = np.array([bracket_span(ts_core, t) > 3.0 for t in grid])
    assert 19 <= in_gap.sum() <= 22  # the 20 s gap, give or take its jittered ends
    np.testing.assert_array_equal(np.isnan(core), in_gap)  # dropped cells bridged (2 s < 3 s)
    ok = ~in_gap
    # samples at most ~2.1 s apart: |f''| h^2 / 8 = 10 (2π/200)^2 (2.1)^2 / 8 = 5.4e-3
    np.testing.assert_allclose(core[ok], 50 + 10 * np.sin(2 * np.pi * grid[ok] / 200),
                               rtol=0, atol=5.5e-3)
    assert result.gaps and result.gaps[0][0] < 300 < 320 < result.gaps[0][1]
    assert result.emptied == {"T_core": int(in_gap.sum())}
    fluid_gap = sum(bracket_span(ts, t) > 3.0 for t in grid)
    assert result.filled == {"T_fluid": int(fluid_gap)}
    assert result.largest_jitter > 0.01


def test_resample_command_writes_a_readable_uniform_run(capsys, tmp_path):
    path, out = tmp_path / "log.csv", tmp_path / "uniform.csv"
    logger_file(path, np.random.default_rng(1))
    rc = main(["resample", "--data", str(path), "--out", str(out), "--dt", "1", "--model",
               str(CONFIGS / "rtd2.toml")])
    printed = capsys.readouterr().out
    assert rc == 0
    tel = read_telemetry(out)  # the reader's uniform check passes
    assert tel.dt == 1.0
    assert np.isfinite(tel.column("T_fluid")).all()  # the model's input, filled
    empty = int(np.isnan(tel.column("T_core")).sum())
    assert 19 <= empty <= 22
    assert "gap(s) longer than 3 s" in printed
    assert f"T_core: {empty} cell(s) left empty" in printed
    header = out.read_text().splitlines()[:3]
    assert header[0].startswith("# written by thermojax resample")
    # running again onto its own output is allowed; onto the logger's own file is not
    assert main(["resample", "--data", str(path), "--out", str(out)]) == 0
    assert main(["resample", "--data", str(out), "--out", str(path)]) == 2
    assert "--force" in capsys.readouterr().err


@pytest.mark.parametrize("argv, fragment", [
    (["--dt", "0"], "--dt"), (["--max-gap", "0.5"], "--max-gap"),
])
def test_resample_bad_arguments(capsys, tmp_path, argv, fragment):
    path = tmp_path / "log.csv"
    logger_file(path, np.random.default_rng(2))
    try:
        rc = main(["resample", "--data", str(path), "--out", str(tmp_path / "u.csv"), *argv])
    except SystemExit as e:  # argparse's own checks
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2 and fragment in err and "Traceback" not in err
