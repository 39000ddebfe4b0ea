"""`export_observer`, `load_observer` and `thermojax export`: the artifact reproduces the
JAX observer (float64 NumPy reference to 1e-9), and its C builds are bit-exact against the
NumPy reference, fault injections included."""

import json
import subprocess

import jax.numpy as jnp
import numpy as np
import pytest

from helpers import CONFIGS
from test_reference_setup import chamber_profile, playback

import thermojax as tj
import thermojax.reference as ref
from thermojax.cli._main import main
from thermojax.observer import design_observer, export_observer, run_observer

DT = 0.05  # 20 Hz


def compile_artifact(folder, prefix):
    exe = folder / f"{prefix}_prog"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-ffp-contract=off", "-o", str(exe), str(folder / f"{prefix}.c"),
                    str(folder / f"{prefix}_main.c"), "-lm"], check=True,
                   capture_output=True, text=True)
    return exe


def run_c(src, exe, folder, x0, u, y, oc=None):
    (folder / "in.bin").write_bytes(src.pack_playback(x0, u, y, oc))
    subprocess.run([str(exe), str(folder / "in.bin"), str(folder / "out.bin")], check=True)
    return src.unpack_output((folder / "out.bin").read_bytes())


def jax_vs_reference(steps, tmp_path, fixed=None):
    model = tj.ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    obs = design_observer(model, DT)
    _, u, y, _, x0 = playback(steps, seed=3)
    want = np.asarray(run_observer(obs, jnp.asarray(u), jnp.asarray(y), jnp.asarray(x0)).states)
    export_observer(CONFIGS / "imu6.toml", 1 / DT, tmp_path / "art", fixed=fixed)
    art = ref.load_observer(tmp_path / "art")
    got = art.float_observer().run(x0, u, y)
    return obs, art, want, got, (u, y, x0)


def test_artifact_reproduces_jax_observer(tmp_path):
    obs, art, want, got, _ = jax_vs_reference(12_000, tmp_path)   # 10 min at 20 Hz
    for name in ("Phi", "B0", "B1", "C", "D"):
        # the same discretization: equal to roundoff
        np.testing.assert_allclose(getattr(art.system, name),
                                   np.asarray(getattr(obs.system, name)), rtol=0, atol=1e-14)
    np.testing.assert_allclose(art.system.L, np.asarray(obs.gain), rtol=0, atol=1e-14)
    assert got.in_use.min() == 7
    np.testing.assert_allclose(got.states, want, rtol=0, atol=1e-9)  # float64 roundoff


@pytest.mark.slow
def test_long_playback_jax_reference_artifact_and_c(tmp_path):
    """Three hours of a chamber profile with noise at 20 Hz (216 000 steps): the float64
    reference from the artifact equals the JAX observer to 1e-9 and the artifact's C
    build bit for bit."""
    obs, art, want, got, (u, y, x0) = jax_vs_reference(216_000, tmp_path)
    diff = np.abs(got.states - want).max()
    print(f"max |reference - JAX| over 3 h: {diff:.3g} K")
    assert diff <= 1e-9  # float64, different summation order only
    folder = tmp_path / "art"
    src = ref.generate_c(art.float_observer(), "tj_observer")
    assert (folder / "tj_observer.c").read_text() == src.source
    c = run_c(src, compile_artifact(folder, "tj_observer"), folder, x0, u, y)
    assert np.array_equal(c.states, got.states)


@pytest.mark.parametrize("fmt", ["q16.16", "q8.24", "q31"])
def test_fixed_c_from_artifact_is_bit_exact_with_faults(fmt, tmp_path):
    export_observer(CONFIGS / "imu6.toml", 1 / DT, tmp_path, fixed=fmt)
    art = ref.load_observer(tmp_path)
    fx = art.fixed_observer()
    _, u, y, _, x0 = playback(12_000, seed=5)
    y = y.copy()
    oc = np.zeros(y.shape, bool)
    y[2000:2300, 1] = 140.0     # implausible: channel dropped, fallback gain
    oc[5000:5200, 2] = True     # open circuit
    X0, U, Y = fx.encode_states(x0), fx.encode_inputs(u), fx.encode_outputs(y)
    want = fx.run(X0, U, Y, oc)
    assert len(set(want.in_use.tolist())) >= 3
    prefix = f"tj_observer_{fmt.replace('.', '_')}"
    src = ref.generate_c(fx, prefix)
    assert (tmp_path / f"{prefix}.c").read_text() == src.source
    got = run_c(src, compile_artifact(tmp_path, prefix), tmp_path, X0, U, Y, oc)
    assert np.array_equal(got.states.astype(np.int64), want.states)
    assert np.array_equal(got.in_use, want.in_use)
    # and it tracks the float reference (quantization only; the derived bound is
    # checked in test_reference_fixed.py)
    xf = art.float_observer().run(x0, u, y, oc).states
    assert np.abs(fx.decode_states(want.states) - xf).max() < 0.05


def test_metadata_and_bias_channels(tmp_path):
    res = export_observer(CONFIGS / "imu6_bias.toml", 20, tmp_path)
    meta = json.loads((tmp_path / "observer.json").read_text())
    assert meta["schema"] == 1 and meta["thermojax_version"] == tj.__version__
    assert meta["rate_hz"] == 20 and meta["dt_s"] == 0.05
    assert meta["plausibility_limits_C"] == [-55.0, 125.0]
    assert [i["hold"] for i in meta["inputs"]] == ["foh", "zoh"]
    assert [i["units"] for i in meta["inputs"]] == ["°C", "W"]
    gyro, accel = meta["biases"]
    assert gyro["coefficients"] == [0.5, 0.03, 5e-4, -2e-6, 0.8, 4.0]
    assert accel["viscoelastic"] == [{"time_constant_s": 1500.0, "k": 0.6, "node": "mems"}]
    assert meta["fixed"] is None and meta["linearization"] is None
    assert len(meta["subsets"]) == 7 and all(s["spectral_radius"] < 1 for s in meta["subsets"])
    assert res.arrays["gain_table"].shape == (8, 6, 3)
    # each fallback gain is the Kalman gain of its own sensors
    sub = design_observer(tj.ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6_bias.toml")),
                          0.05, sensors=["T_housing", "T_asic"])
    np.testing.assert_allclose(res.arrays["gain_table"][0b101][:, [0, 2]],
                               np.asarray(sub.gain), rtol=0, atol=1e-14)  # same computation


def test_q15_warns_naming_the_coupling(tmp_path):
    """At 1 kHz the per-step couplings (g dt / C) of the weak links fall below Q15's LSB."""
    with pytest.warns(UserWarning, match=r"q15 .* rounds .* to zero.*Phi\[pcb, mems\]"):
        res = export_observer(CONFIGS / "imu6.toml", 1000, tmp_path, fixed="q15")
    assert res.metadata["fixed"]["format"] == "q15"
    assert ref.load_observer(tmp_path).fixed_observer().fmt.name == "q15"


def test_range_too_small_is_an_error(tmp_path):
    narrow = ref.FixedFormat("q15", 16, 15, 64.0)    # ±64 K around 35 °C: not -55..125
    with pytest.raises(tj.InputError, match="field '--fixed'.*cannot hold the limits"):
        export_observer(CONFIGS / "imu6.toml", 20, tmp_path, fixed=narrow)


def test_nonlinear_model_is_linearized_with_a_warning(tmp_path):
    text = (CONFIGS / "imu6.toml").read_text() + (
        '\n[[effects]]\nkind = "radiation"\nwhere = ["housing", "T_chamber"]\n'
        'coefficient = 2e-10\n')
    path = tmp_path / "imu6_rad.toml"
    path.write_text(text)
    with pytest.warns(UserWarning, match=r"radiation.*linearization at a uniform 25 °C"):
        res = export_observer(path, 20, tmp_path / "art")
    lin = res.metadata["linearization"]
    assert lin["operating_point_C"] == 25.0 and lin["effects"]
    # the radiative conductance 4 k T³ adds to the boundary's: Phi differs from imu6's
    plain = export_observer(CONFIGS / "imu6.toml", 20, tmp_path / "plain")
    g_rad = 4 * 2e-10 * (25 + 273.15) ** 3
    assert not np.allclose(res.arrays["Phi"], plain.arrays["Phi"])
    # a uniform temperature stays an equilibrium (no constant term)
    a = res.arrays
    x = np.full(6, 60.0)
    np.testing.assert_allclose(a["Phi"] @ x + (a["B0"] + a["B1"]) @ [60.0, 0.0], x,
                               rtol=0, atol=1e-10)
    assert g_rad > 0


def test_load_observer_errors(tmp_path):
    export_observer(CONFIGS / "imu6.toml", 20, tmp_path)
    meta = json.loads((tmp_path / "observer.json").read_text())
    meta["schema"] = 2
    (tmp_path / "observer.json").write_text(json.dumps(meta))
    with pytest.raises(ref.ArtifactError, match=r"observer.json, field 'schema': schema "
                                                r"version 2.*reads schema 1"):
        ref.load_observer(tmp_path)
    meta["schema"] = 1
    (tmp_path / "observer.json").write_text(json.dumps(meta))
    arrays = dict(np.load(tmp_path / "observer.npz"))
    del arrays["gain_table"]
    np.savez(tmp_path / "observer.npz", **arrays)
    with pytest.raises(ValueError, match=r"observer.npz, field 'gain_table': the array "
                                         r"'gain_table' is missing"):
        ref.load_observer(tmp_path)
    with pytest.raises(ref.ArtifactError, match="no observer.json"):
        ref.load_observer(tmp_path / "nowhere")


def test_cli_export_and_check(tmp_path, capsys):
    out = tmp_path / "obs"
    assert main(["export", "--model", "imu6", "--rate", "20", "--out", str(out),
                 "--fixed", "q16.16", "--quiet", "--no-cache"]) == 0
    assert (out / "tj_observer_q16_16.c").is_file() and (out / "tj_observer.h").is_file()
    assert "observer.npz" in capsys.readouterr().out
    assert main(["export", "--check", str(out)]) == 0
    # a second run replaces its own folder; a foreign folder needs --force
    assert main(["export", "--model", "imu6", "--rate", "10", "--out", str(out), "--quiet",
                 "--no-cache"]) == 0
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(["export", "--model", "imu6", "--rate", "10", "--out", str(foreign),
                 "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err


def test_cli_export_float32_columns_build_equals_the_reference(tmp_path):
    """`--c-float float32 --c-layout columns`: the vectorizable float32 build (the one
    benchmarks/observer_c.py counts), compiled with warnings as errors, plays back equal
    to the artifact's float32 reference (up to the sign of an exact zero), flags exactly."""
    from test_reference_c_columns import same_up_to_zero_sign

    out = tmp_path / "obs"
    assert main(["export", "--model", "imu6", "--rate", "20", "--out", str(out), "--quiet",
                 "--no-cache", "--c-float", "float32", "--c-layout", "columns"]) == 0
    art = ref.load_observer(out)
    assert art.metadata["c_build"] == {"float": "float32", "layout": "columns"}
    text = (out / "tj_observer.c").read_text()
    assert "typedef float tj_observer_word_t;" in (out / "tj_observer.h").read_text()
    assert "TJ_OBSERVER_COLS" in text
    _, u, y, _, x0 = playback(6_000, seed=5)
    y = y.copy()
    y[2000:2400, 1] = 300.0   # a channel out of its plausible range for 20 s
    want = art.float_observer(np.float32).run(x0, u, y)
    src = ref.generate_c(art.float_observer(np.float32), "tj_observer", layout="columns")
    assert src.source == text
    got = run_c(src, compile_artifact(out, "tj_observer"), out, x0, u, y)
    assert same_up_to_zero_sign(got.states, want.states)
    assert np.array_equal(got.in_use, want.in_use) and got.in_use[2100] == 0b101


@pytest.mark.parametrize("argv, match", [
    (["--sensor", "T_housing"], r"imu6.toml, field '--sensor'.*unobservable.*involving asic"
                                r".*A sensor on pcb"),
    (["--rate", "0.001"], r"field '--rate'.*decay to nothing within one sample"),
])
def test_cli_bad_input_exits_2(argv, match, tmp_path, capsys):
    base = {"--model": str(CONFIGS / "imu6.toml"), "--rate": "20", "--out": str(tmp_path / "o")}
    args = ["export", "--quiet", "--no-cache"]
    for k, v in base.items():
        if k not in argv:
            args += [k, v]
    assert main(args + argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    import re
    assert re.search(match, err), err
    assert not (tmp_path / "o").exists()


def test_cli_check_other_schema_exits_2(tmp_path, capsys):
    export_observer(CONFIGS / "imu6.toml", 20, tmp_path)
    meta = json.loads((tmp_path / "observer.json").read_text())
    meta["schema"] = 7
    (tmp_path / "observer.json").write_text(json.dumps(meta))
    assert main(["export", "--check", str(tmp_path)]) == 2
    assert "schema version 7" in capsys.readouterr().err


def test_chamber_profile_in_range():
    u = chamber_profile(1000)
    assert u.shape == (1000, 2)
