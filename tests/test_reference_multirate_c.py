"""The multi-rate split in C (issue 34, item 4): the exported imu6_bias observer's C
runs at 20 Hz and publishes its bias channels; the generated double buffer and
interpolator (`tj_multirate.c`) ramp them at 2 kHz. Both against the NumPy reference
(`run_multirate`), bit for bit, with publications late by random ticks (jitter)."""

from __future__ import annotations

import json
import subprocess

import numpy as np

from helpers import CONFIGS
from test_reference_bias import plant
from test_reference_setup import DT

import thermojax.reference as ref
from thermojax.cli import main

STEPS, RATIO = 1200, 100          # one minute at 20 Hz, ticks at 2 kHz


def _gcc(folder, prefix):
    exe = folder / f"{prefix}_prog"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-ffp-contract=off", "-o", str(exe), str(folder / f"{prefix}.c"),
                    str(folder / f"{prefix}_main.c"), "-lm"], check=True, capture_output=True,
                   text=True)
    return exe


def test_thermal_and_inertial_rates_in_c_equal_the_reference(tmp_path):
    out = tmp_path / "obs"
    assert main(["export", "--model", str(CONFIGS / "imu6_bias.toml"), "--rate",
                 str(1 / DT), "--inertial-rate", str(RATIO / DT), "--out", str(out),
                 "--quiet"]) == 0
    meta = json.loads((out / "observer.json").read_text())
    assert meta["multirate"]["ratio"] == RATIO
    art = ref.load_observer(out)
    net, u, x, y, x0 = plant(STEPS, seed=2)
    y = y + 0.01 * np.random.default_rng(0).standard_normal(y.shape)
    delay = np.random.default_rng(1).integers(0, RATIO, STEPS)     # the thermal task's jitter
    want = ref.run_multirate(art.float_observer(), x0, u, y, ratio=RATIO, delay_ticks=delay)
    # the thermal rate: the observer's C evaluates the same bias channels, bit for bit
    obs = art.float_observer()
    src = ref.generate_c(obs, "tj_observer", art.names)
    (out / "in.bin").write_bytes(src.pack_playback(x0, u, y))
    subprocess.run([str(_gcc(out, "tj_observer")), str(out / "in.bin"), str(out / "out.bin")],
                   check=True)
    thermal = src.unpack_output((out / "out.bin").read_bytes()).bias
    assert np.array_equal(thermal, want.bias)
    # the inertial rate: the C double buffer and ramps from the C's own publications
    ev = art.bias_evaluator()
    b0 = ev.step(np.asarray(x0, float), np.asarray(u[0], float))
    mr = ref.generate_multirate_c("tj_multirate", thermal.shape[1], RATIO)
    assert (out / "tj_multirate.c").read_text() == mr.source
    (out / "mr.bin").write_bytes(ref.pack_multirate(b0, thermal, delay))
    subprocess.run([str(_gcc(out, "tj_multirate")), str(out / "mr.bin"),
                    str(out / "mr_out.bin")], check=True)
    got = np.frombuffer((out / "mr_out.bin").read_bytes(), np.float64).reshape(-1, 2)
    assert got.shape == want.inertial.shape == (STEPS * RATIO, 2)
    assert np.array_equal(got, want.inertial)
    # and the ramps are what the design says: continuous, each tick a fraction of a step
    steps = np.abs(np.diff(want.bias, axis=0)).max(axis=0)
    assert np.all(np.abs(np.diff(got, axis=0)).max(axis=0) <= 2 * steps / RATIO + 1e-12)


def test_inertial_rate_mistakes(tmp_path, capsys):
    assert main(["export", "--model", str(CONFIGS / "imu6_bias.toml"), "--rate", "20",
                 "--inertial-rate", "2010", "--out", str(tmp_path / "a"), "--quiet"]) == 2
    assert "whole multiple" in capsys.readouterr().err
    assert main(["export", "--model", "rtd2", "--rate", "20", "--inertial-rate", "2000",
                 "--out", str(tmp_path / "b"), "--quiet"]) == 2
    assert "no bias channel" in capsys.readouterr().err
