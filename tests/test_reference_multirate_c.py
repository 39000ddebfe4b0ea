"""The multi-rate split in C (issue 34, item 4): the exported imu6_bias observer's C
runs at 20 Hz and publishes its bias channels; the generated double buffer and
interpolator (`tj_multirate.c`) ramp them at 2 kHz. Both against the NumPy reference
(`run_multirate`), bit for bit, with publications late by random ticks (jitter); the
fixed-point build's int32 bias codes the same way (`tj_multirate_q16_16.c`), and its
ramps against exact rational arithmetic."""

from __future__ import annotations

import json
import math
import subprocess
from fractions import Fraction

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


def _exact_ramps(initial, bias, at, ratio, ticks):
    """The first `ticks` inertial outputs written from the rule in words: at a new
    publication the ramp starts from the current output; tick i of R outputs the code
    nearest start + (target − start)·i/R (ties up), tick R the target. Fractions, no
    floor division of negative integers."""
    out, start, target, i, k = list(initial), list(initial), list(initial), ratio, 0
    rows = []
    for t in range(ticks):
        while k < len(at) and at[k] == t:
            start, target, i, k = list(out), [int(v) for v in bias[k]], 0, k + 1
        if i < ratio:
            i += 1
            out = [b if i == ratio else a + math.floor(Fraction((b - a) * i, ratio)
                                                          + Fraction(1, 2))
                   for a, b in zip(start, target)]
        rows.append(out)
    return np.array(rows, np.int64)


def test_fixed_point_bias_codes_ramp_in_integers_in_c(tmp_path):
    """`export --fixed q16.16 --inertial-rate`: the fixed build's C publishes int32 bias
    codes and `tj_multirate_q16_16.c` ramps them in int64 arithmetic, both bit-exact with
    `run_multirate` on the `FixedObserver`; the ramps are the nearest codes of the exact
    line, and decoded they follow the float build's ramps within the fixed error."""
    out = tmp_path / "obs"
    assert main(["export", "--model", str(CONFIGS / "imu6_bias.toml"), "--rate",
                 str(1 / DT), "--inertial-rate", str(RATIO / DT), "--fixed", "q16.16",
                 "--out", str(out), "--quiet"]) == 0
    meta = json.loads((out / "observer.json").read_text())
    fixed_meta = meta["multirate"]["fixed"]
    assert fixed_meta["prefix"] == "tj_multirate_q16_16" and fixed_meta["word"] == "int32_t"
    art = ref.load_observer(out)
    fx = art.fixed_observer()
    assert fixed_meta["bias_frac_bits"] == [int(g) for g in fx.biases.g]
    net, u, x, y, x0 = plant(STEPS, seed=4)
    y = y + 0.01 * np.random.default_rng(3).standard_normal(y.shape)
    delay = np.random.default_rng(5).integers(0, RATIO, STEPS)
    X0, U, Y = fx.encode_states(x0), fx.encode_inputs(u), fx.encode_outputs(y)
    want = ref.run_multirate(fx, X0, U, Y, ratio=RATIO, delay_ticks=delay)
    assert want.inertial.dtype == np.int64
    # the thermal rate: the fixed C's bias codes
    src = ref.generate_c(fx, "tj_observer_q16_16", art.names)
    (out / "in.bin").write_bytes(src.pack_playback(X0, U, Y))
    subprocess.run([str(_gcc(out, "tj_observer_q16_16")), str(out / "in.bin"),
                    str(out / "out.bin")], check=True)
    thermal = src.unpack_output((out / "out.bin").read_bytes()).bias
    assert np.array_equal(thermal, want.bias)
    # the inertial rate: int32 double buffer and integer ramps in C
    fx.biases.reset()
    b0 = fx.biases.step(X0, U[0])
    mr = ref.generate_multirate_c("tj_multirate_q16_16", 2, RATIO, word="int32_t")
    assert (out / "tj_multirate_q16_16.c").read_text() == mr.source
    assert "double" not in mr.source and "float" not in mr.source
    (out / "mr.bin").write_bytes(ref.pack_multirate(b0, thermal, delay, word="int32_t"))
    subprocess.run([str(_gcc(out, "tj_multirate_q16_16")), str(out / "mr.bin"),
                    str(out / "mr_out.bin")], check=True)
    got = np.frombuffer((out / "mr_out.bin").read_bytes(), np.int32).reshape(-1, 2)
    assert got.shape == (STEPS * RATIO, 2)
    assert np.array_equal(got.astype(np.int64), want.inertial)
    # the ramps against exact rationals (the first 40 thermal steps: 4,000 ticks, with
    # ramps of either sign and ties)
    ticks = 40 * RATIO
    exact = _exact_ramps(b0, want.bias, want.published_at, RATIO, ticks)
    assert np.array_equal(want.inertial[:ticks], exact)
    assert np.any(np.diff(want.bias[:40], axis=0) < 0) and np.any(np.diff(want.bias[:40],
                                                                           axis=0) > 0)
    # decoded, the fixed ramps follow the float build's within its bias error plus a code
    flt = ref.run_multirate(art.float_observer(), x0, u, y, ratio=RATIO, delay_ticks=delay)
    thermal_err = np.abs(fx.decode_bias(want.bias) - flt.bias).max(0)
    inertial_err = np.abs(fx.decode_bias(want.inertial) - flt.inertial).max(0)
    assert np.all(inertial_err <= thermal_err + fx.biases.lsb), (inertial_err, thermal_err)


def test_inertial_rate_mistakes(tmp_path, capsys):
    assert main(["export", "--model", str(CONFIGS / "imu6_bias.toml"), "--rate", "20",
                 "--inertial-rate", "2010", "--out", str(tmp_path / "a"), "--quiet"]) == 2
    assert "whole multiple" in capsys.readouterr().err
    assert main(["export", "--model", "rtd2", "--rate", "20", "--inertial-rate", "2000",
                 "--out", str(tmp_path / "b"), "--quiet"]) == 2
    assert "no bias channel" in capsys.readouterr().err
