"""Channel supervision from the command line: `export` records the fault flags in the
artifact, and `playback` injects sensor faults into a log and plays it through the
reference observer. Expected flag timings follow from the documented rules
(docs/cli.md, `thermojax.reference._faults`) and the injected windows, not from the
code under test; the log comes from `scipy.signal.lsim` of the model's matrices."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.signal

import thermojax as tj
from thermojax.cli import main

from helpers import CONFIGS, model_matrices

DT = 1.0
MODEL = str(CONFIGS / "rtd2.toml")


def _log(tmp_path, seconds=900.0, seed=0):
    """The fluid ramping 25 -> 60 °C and back, the core sensor with 0.01 °C noise."""
    rng = np.random.default_rng(seed)
    ts = DT * np.arange(int(seconds / DT) + 1)
    fluid = 25.0 + 35.0 * np.clip(np.minimum(ts - 60.0, seconds - 60.0 - ts) / 300.0, 0, 1)
    m = model_matrices(CONFIGS / "rtd2.toml")
    x0 = np.linalg.solve(m["A"], -m["B"][:, 0] * fluid[0])
    _, y, _ = scipy.signal.lsim((m["A"], m["B"], m["Cy"], np.zeros((1, 1))), fluid, ts,
                                X0=x0, interp=True)
    reading = np.asarray(y).reshape(-1) + 0.01 * rng.standard_normal(ts.size)
    path = tmp_path / "log.csv"
    tj.write_telemetry(path, ts, {"T_fluid": fluid, "T_core": reading})
    return path, ts


@pytest.fixture(scope="module")
def artifact(tmp_path_factory):
    out = tmp_path_factory.mktemp("art") / "obs"
    assert main(["export", "--model", MODEL, "--rate", "1", "--out", str(out), "--fixed",
                 "q16.16", "--limits", "-50", "120", "--rails", "-40", "100",
                 "--wire-break-threshold", "1.5", "--wire-break-after", "3",
                 "--recover-after", "4", "--quiet"]) == 0
    return out


def test_export_records_the_supervision_flags(artifact, capsys):
    meta = json.loads((artifact / "observer.json").read_text())
    expected = {"limits_C": [-50.0, 120.0], "rails_C": [[-40.0, 100.0]],
                "residual_threshold_K": [1.5], "wire_break_after": 3, "recover_after": 4}
    assert {k: meta["faults"][k] for k in expected} == expected
    art = tj.reference.load_observer(artifact)
    assert art.faults.limits == (-50.0, 120.0)
    np.testing.assert_array_equal(art.faults.rails_array(1), [[-40.0, 100.0]])
    np.testing.assert_array_equal(art.faults.threshold_array(1), [1.5])
    assert (art.faults.wire_break_after, art.faults.recover_after) == (3, 4)
    # the C of the artifact carries them too (the reference and C are checked bit for
    # bit elsewhere): the rails and the threshold appear as constants of the float build
    c = (artifact / "tj_observer.c").read_text()
    assert "100" in c and "1.5" in c


@pytest.mark.parametrize("flags, field", [
    (["--limits", "5", "1"], "--limits"),
    (["--rails", "130", "150"], "--rails"),
    (["--rails", "10", "-10"], "--rails"),
    (["--wire-break-after", "0"], "--wire-break-after"),
    (["--wire-break-threshold", "-1"], "--wire-break-threshold"),
])
def test_export_refuses_bad_supervision_flags(tmp_path, capsys, flags, field):
    with pytest.raises(SystemExit) if field.startswith("--wire") else _no_raise():
        code = main(["export", "--model", MODEL, "--rate", "1", "--out",
                     str(tmp_path / "o"), *flags, "--quiet"])
        assert code == 2
    assert field in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


class _no_raise:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _masks(out):
    got = tj.read_telemetry(out)
    return got, got.column("in_use").astype(int), got.column("wire_break").astype(int)


def test_wire_break_is_flagged_after_n_samples_and_recovers_after_m(tmp_path, artifact,
                                                                     capsys):
    log, ts = _log(tmp_path)
    out = tmp_path / "play.csv"
    assert main(["playback", str(artifact), "--data", str(log), "--out", str(out),
                 "--inject", "wire-break:T_core:300:400", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "wire-break on T_core at 300–400 s: bounded" in text and "recovered" in text
    got, in_use, wire = _masks(out)
    k0, k1 = 300, 400          # the window's first and last samples (dt = 1 s)
    # 10 K off against a 1.5 K threshold: samples k0, k0+1, k0+2 are large; the third
    # (N = 3) raises the flag and drops the only channel
    assert np.all(wire[:k0 + 2] == 0) and np.all(wire[k0 + 2:k1 + 1] == 1)
    assert np.all(in_use[k0:k0 + 2] == 1) and np.all(in_use[k0 + 2:k1 + 1] == 0)
    # after the window the prediction (exact model) is still within the threshold, so
    # M = 4 good samples bring it back: in use again at k1 + 4
    assert np.all(in_use[k1 + 1:k1 + 4] == 0) and np.all(in_use[k1 + 4:] == 1)
    assert np.all(wire[k1 + 4:] == 0)
    est, clean = got.column("T_core_estimate"), got.column("T_core_clean")
    assert np.abs(est - clean)[-100:].max() < 0.05
    assert np.all(np.isfinite(est))
    assert out.with_suffix(".png").stat().st_size > 10_000


@pytest.mark.parametrize("build", ["float64", "float32", "fixed"])
def test_each_fault_kind_stays_bounded_and_recovers(tmp_path, artifact, capsys, build):
    log, ts = _log(tmp_path)
    out = tmp_path / "play.csv"
    faults = ["rail:T_core:100:150", "open:T_core:200:260", "dropout:T_core:300:330",
              "spike:T_core:450", "stuck:T_core:500:560", "wire-break:T_core:650:700"]
    args = ["playback", str(artifact), "--data", str(log), "--out", str(out),
            "--build", build, "--quiet"]
    for f in faults:
        args += ["--inject", f]
    assert main(args) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if " on T_core at " in ln]
    assert len(lines) == len(faults)
    assert all(": bounded" in ln and "recovered" in ln and "NOT" not in ln for ln in lines)
    got, in_use, wire = _masks(out)
    reading = got.column("T_core_reading")
    # at the rail (100 °C, the high rail) the channel is left out: anti-windup
    assert np.all(reading[100:151] == 100.0) and np.all(in_use[100:151] == 0)
    assert np.all(in_use[200:261] == 0) and np.all(in_use[300:331] == 0)
    assert np.all(np.isnan(reading[300:331]))
    # a spike of 30 K is one large residual: fewer than N, so the channel stays in use
    assert reading[450] - got.column("T_core_clean")[450] > 25 and in_use[450] == 1


def test_playback_mistakes_are_named(tmp_path, artifact, capsys):
    log, ts = _log(tmp_path, seconds=120.0)
    out = tmp_path / "p.csv"
    base = ["playback", str(artifact), "--data", str(log), "--out", str(out), "--quiet"]
    for inject, words in [("melt:T_core:1:2", "KIND"), ("open:T_case:1:2", "not a sensor"),
                          ("open:T_core:5:2", "START < END"),
                          ("open:T_core:500:600", "outside the log"),
                          ("spike:T_core:1:2:3", "spike:COLUMN:TIME")]:
        assert main([*base, "--inject", inject]) == 2
        assert words in capsys.readouterr().err
    slow = tmp_path / "slow.csv"
    t = 2.0 * np.arange(30)
    tj.write_telemetry(slow, t, {"T_fluid": np.full(30, 25.0), "T_core": np.full(30, 25.0)})
    assert main(["playback", str(artifact), "--data", str(slow), "--out", str(out),
                 "--quiet"]) == 2
    assert "resample" in capsys.readouterr().err
    bare = tmp_path / "bare"
    assert main(["export", "--model", MODEL, "--rate", "1", "--out", str(bare),
                 "--quiet"]) == 0
    assert main(["playback", str(bare), "--data", str(log), "--out", str(out),
                 "--inject", "rail:T_core:10:20", "--quiet"]) == 2
    assert "--rails" in capsys.readouterr().err
    assert main(["playback", str(bare), "--data", str(log), "--out", str(out),
                 "--build", "fixed", "--quiet"]) == 2
    assert "--fixed" in capsys.readouterr().err


def test_bad_input_samples_are_held_and_flagged(tmp_path, artifact, capsys):
    log, ts = _log(tmp_path)
    got = tj.read_telemetry(log)
    fluid = np.array(got.column("T_fluid"))
    fluid[200], fluid[400:403] = np.nan, 1e6          # a dropped and an absurd input
    bad = tmp_path / "bad.csv"
    tj.write_telemetry(bad, got.ts, {"T_fluid": fluid, "T_core": got.column("T_core")})
    out = tmp_path / "play.csv"
    assert main(["playback", str(artifact), "--data", str(bad), "--out", str(out),
                 "--quiet"]) == 0
    assert "4 samples with an input held" in capsys.readouterr().out
    played = tj.read_telemetry(out)
    flags = played.column("input_fault").astype(int)
    assert np.array_equal(np.flatnonzero(flags), [200, 400, 401, 402])
    assert np.all(np.isfinite(played.column("T_core_estimate")))
    assert np.all(played.column("state_ok") == 1)



def test_gating_ignores_a_spike_and_rejects_an_offset(tmp_path, capsys):
    """With --gate a sample over the threshold does not correct: the spike's sample is
    left out (the channel stays healthy), and an offset is refused from its first
    sample until the wire-break flag rises at the N-th."""
    out = tmp_path / "g"
    assert main(["export", "--model", MODEL, "--rate", "1", "--out", str(out),
                 "--wire-break-threshold", "1.5", "--wire-break-after", "3",
                 "--recover-after", "4", "--gate", "--quiet"]) == 0
    assert "gated" in capsys.readouterr().out
    log, ts = _log(tmp_path)
    play = tmp_path / "p.csv"
    assert main(["playback", str(out), "--data", str(log), "--out", str(play),
                 "--inject", "spike:T_core:450", "--inject", "wire-break:T_core:600:700",
                 "--quiet"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if " on T_core " in ln]
    spike = next(ln for ln in lines if ln.startswith("spike"))
    got, in_use, wire = _masks(play)
    assert in_use[450] == 0 and in_use[449] == 1 and in_use[451] == 1 and wire[450] == 0
    assert np.all(in_use[600:701] == 0)           # never absorbed
    assert np.all(wire[602:701] == 1) and np.all(wire[:602] == 0)
    worst = float(spike.split("worst ")[1].split(" K")[0])
    assert worst < 0.05                           # the spike never reached the estimate
    # gating needs a threshold
    assert main(["export", "--model", MODEL, "--rate", "1", "--out", str(tmp_path / "h"),
                 "--gate", "--quiet"]) == 2
    assert "--wire-break-threshold" in capsys.readouterr().err
