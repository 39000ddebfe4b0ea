"""The `thermojax` command line (formats spec §5): help, simulate, demo, and bad input.

Most runs call `thermojax.cli.main([...])` in-process (fast); a few run a real
subprocess to prove the exit status, the float64 switch and the absence of a
traceback as a user sees them.
"""

import os
import re
import subprocess
import sys

import numpy as np
import pytest

from thermojax import InputError, io
from thermojax.model._model_file import load_model
from thermojax.measurements._telemetry import Telemetry, read_telemetry, write_telemetry
from thermojax.cli import main

from helpers import CONFIGS, ROOT

RTD2 = str(CONFIGS / "rtd2.toml")


def run(capsys, *argv):
    """`thermojax argv...` in-process: (exit status, stdout, stderr)."""
    capsys.readouterr()
    try:
        rc = main(list(argv))
    except SystemExit as e:  # argparse: --help, usage errors
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def run_process(*argv, cwd=None):
    """`python -m thermojax.cli argv...` as a real process."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.run([sys.executable, "-m", "thermojax.cli", *map(str, argv)],
                          capture_output=True, text=True, cwd=cwd or ROOT, env=env, timeout=300)


def assert_user_error(rc, err, *fragments):
    """Exit 2, one paragraph on stderr naming each fragment (file, line, field), no traceback."""
    assert rc == 2, err
    assert "Traceback" not in err
    assert err.startswith("thermojax ") and "error: " in err
    assert err.strip().count("\n") == 0, err  # one paragraph
    for fragment in fragments:
        assert fragment in err, (fragment, err)


# ---------------------------------------------------------------------------
# help


@pytest.mark.parametrize("argv", [["--help"], ["simulate", "--help"], ["demo", "--help"]])
def test_help(capsys, argv):
    rc, out, err = run(capsys, *argv)
    assert rc == 0
    assert out.startswith("usage: thermojax")
    assert err == ""


def test_help_lists_commands_and_options(capsys):
    _, out, _ = run(capsys, "--help")
    assert "simulate" in out and "demo" in out
    _, out, _ = run(capsys, "simulate", "--help")
    for option in ("--model", "--profile", "--out", "--noise", "--seed"):
        assert option in out


def test_console_script_help():
    """The installed `thermojax` script (or, without it, the module) prints usage."""
    script = os.path.join(os.path.dirname(sys.executable), "thermojax")
    cmd = [script] if os.path.exists(script) else [sys.executable, "-m", "thermojax.cli"]
    proc = subprocess.run([*cmd, "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    assert proc.stdout.startswith("usage: thermojax")


def test_usage_error_exits_2(capsys):
    rc, out, err = run(capsys, "simulate", "--profile", "shock", "--out", "x.csv")
    assert rc == 2
    assert "the following arguments are required: --model" in err
    assert "Traceback" not in err


# ---------------------------------------------------------------------------
# simulate


@pytest.fixture(scope="module")
def shock_runs(tmp_path_factory):
    """rtd2 through the built-in shock profile: clean, noisy (seed 3) twice, noisy seed 4."""
    d = tmp_path_factory.mktemp("shock")
    paths = {}
    for key, extra in [("clean", []), ("noisy3", ["--noise", "--seed", "3"]),
                       ("noisy3b", ["--noise", "--seed", "3"]),
                       ("noisy4", ["--noise", "--seed", "4"])]:
        paths[key] = d / f"{key}.csv"
        rc = main(["simulate", "--model", RTD2, "--profile", "shock", "--out",
                   str(paths[key]), *extra])
        assert rc == 0
    return paths


def test_simulate_writes_readable_csv(shock_runs):
    tel = read_telemetry(shock_runs["clean"])
    assert tel.names == ("T_fluid", "T_core")
    assert len(tel) == 4201  # 600 s + 3600 s at 1 s
    assert tel.dt == 1.0
    np.testing.assert_array_equal(tel.ts, np.arange(4201.0))
    assert tel.column("T_fluid")[0] == 25.0 and tel.column("T_fluid")[-1] == 85.0
    core = tel.column("T_core")
    # Starts at the steady state of the first input; after 1 h (~10 time constants of
    # the 0.8+0.1 J/K, 0.2 W/K model) sits at the fluid temperature. float64 roundoff.
    np.testing.assert_allclose(core[:600], 25.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(core[-1], 85.0, rtol=0, atol=1e-6)
    assert np.all(np.diff(core) >= -1e-9)  # a heating step: the core only warms


def test_simulate_prints_summary(capsys, tmp_path):
    rc, out, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                       "--out", str(tmp_path / "x.csv"))
    assert rc == 0 and err == ""
    assert "4201 samples" in out and "T_core" in out


def test_simulate_noise_std(shock_runs):
    clean = read_telemetry(shock_runs["clean"]).column("T_core")
    noisy = read_telemetry(shock_runs["noisy3"]).column("T_core")
    noise = noisy - clean
    sigma = load_model(RTD2).sensors[0].noise.value
    assert sigma == 0.01
    # 4201 samples: the std estimate's relative error is ~1/sqrt(2 N) ~ 1.1 %; 10 % is ~9 sigma.
    assert abs(np.std(noise) / sigma - 1) < 0.10
    assert abs(np.mean(noise)) < 5 * sigma / np.sqrt(len(noise))  # zero mean
    # The inputs are not noisy.
    np.testing.assert_array_equal(read_telemetry(shock_runs["noisy3"]).column("T_fluid"),
                                  read_telemetry(shock_runs["clean"]).column("T_fluid"))


def test_simulate_same_seed_same_file(shock_runs):
    assert shock_runs["noisy3"].read_bytes() == shock_runs["noisy3b"].read_bytes()
    assert shock_runs["noisy3"].read_bytes() != shock_runs["noisy4"].read_bytes()


def test_simulate_builtin_model_name(capsys, tmp_path):
    out = tmp_path / "imu.csv"
    rc, stdout, err = run(capsys, "simulate", "--model", "imu6", "--profile", "power_step",
                          "--out", str(out), "--states")
    assert rc == 0, err
    tel = read_telemetry(out)
    spec = load_model(CONFIGS / "imu6.toml")
    assert tel.names == (*spec.input_columns, *spec.sensor_columns,
                         *(f"state_{n}" for n in spec.node_names))
    np.testing.assert_array_equal(tel.column("T_pcb"), tel.column("state_pcb"))
    # 1 W into the ASIC from a 25 °C steady state warms every node; the ASIC most.
    assert tel.column("state_asic").max() > tel.column("state_pcb").max() > 25.0


def test_simulate_profile_from_csv(capsys, tmp_path):
    ts = np.arange(0.0, 300.0, 2.0)
    fluid = np.where(ts < 50, 20.0, 60.0)
    write_telemetry(tmp_path / "drive.csv", ts, {"T_fluid": fluid, "other": ts * 0},
                    comments=["chamber run 7"])
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile",
                     str(tmp_path / "drive.csv"), "--out", str(tmp_path / "sim.csv"))
    assert rc == 0, err
    tel = read_telemetry(tmp_path / "sim.csv")
    assert tel.names == ("T_fluid", "T_core")
    np.testing.assert_array_equal(tel.ts, ts)
    np.testing.assert_array_equal(tel.column("T_fluid"), fluid)
    core = tel.column("T_core")
    np.testing.assert_allclose(core[:25], 20.0, rtol=0, atol=1e-9)  # steady state; roundoff
    assert 20.0 < core[-1] <= 60.0 + 1e-9 and np.all(np.diff(core) >= -1e-9)  # settled: roundoff


def test_simulate_subprocess_float64(tmp_path):
    """A real process: exit 0, and float64 (the steady state 25 °C is kept to roundoff;
    float32 would be off by ~2e-6)."""
    out = tmp_path / "x.csv"
    proc = run_process("simulate", "--model", "configs/rtd2.toml", "--profile", "shock",
                       "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    core = read_telemetry(out).column("T_core")
    np.testing.assert_allclose(core[:600], 25.0, rtol=0, atol=1e-9)  # float64 roundoff only


# ---------------------------------------------------------------------------
# bad profile CSVs: exit 2 naming the file, the line and the column

BAD_CSV = [
    ("missing-column", "time_s,T_air\n0,20\n1,21\n2,22\n",
     ["'T_fluid'", "available columns are: T_air"]),
    ("not-increasing", "time_s,T_fluid\n0,20\n1,21\n1,22\n2,22\n",
     ["line 4", "'time_s'", "strictly increasing"]),
    ("decreasing", "# a comment\ntime_s,T_fluid\n0,20\n1,21\n2,22\n1.5,22\n",
     ["line 6", "'time_s'", "strictly increasing"]),
    ("non-numeric", "time_s,T_fluid\n0,20\n1,warm\n2,22\n",
     ["line 3", "field 'T_fluid'", "'warm'", "not a number"]),
    ("empty-file", "", ["no header"]),
    ("only-comments", "# nothing here\n", ["no header"]),
    ("header-only", "time_s,T_fluid\n", ["no data rows"]),
    ("nan-input", "time_s,T_fluid\n0,20\n1,21\n2,nan\n3,22\n",
     ["line 4", "'T_fluid'", "empty or not finite"]),
    ("empty-input-cell", "time_s,T_fluid\n0,20\n1,\n2,21\n3,22\n",
     ["line 3", "'T_fluid'", "empty or not finite"]),
    ("inf-input", "time_s,T_fluid\n0,20\n1,21\n2,22\n3,inf\n",
     ["line 5", "'T_fluid'", "not finite"]),
    ("ragged-row", "time_s,T_fluid\n0,20\n1,21,5\n2,22\n", ["line 3", "3 cells"]),
    ("wrong-first-column", "T_fluid,time_s\n20,0\n21,1\n", ["line 1", "'time_s'"]),
    ("irregular", "time_s,T_fluid\n0,20\n1,21\n2,22\n5,22\n6,22\n",
     ["line 5", "irregular sampling"]),
]


@pytest.mark.parametrize("text,fragments", [c[1:] for c in BAD_CSV], ids=[c[0] for c in BAD_CSV])
def test_simulate_bad_profile_csv(capsys, tmp_path, text, fragments):
    path = tmp_path / "bad_profile.csv"
    path.write_text(text)
    rc, out, err = run(capsys, "simulate", "--model", RTD2, "--profile", str(path),
                       "--out", str(tmp_path / "x.csv"))
    assert_user_error(rc, err, str(path), *fragments)
    assert not (tmp_path / "x.csv").exists()


def test_simulate_missing_column_lists_available(capsys, tmp_path):
    path = tmp_path / "other.csv"
    path.write_text("time_s,T_air,P_x\n0,20,0\n1,21,0\n")
    rc, _, err = run(capsys, "simulate", "--model", "imu6", "--profile", str(path),
                     "--out", str(tmp_path / "x.csv"))
    assert_user_error(rc, err, str(path), "no column 'T_chamber'",
                      "available columns are: T_air, P_x")


@pytest.mark.parametrize("argv,fragments", [
    (["--profile", "nowhere.csv"], ["nowhere.csv", "no such file", "--profile"]),
    (["--profile", "sunrise"], ["'sunrise'", "built-in profile", "--profile"]),
    (["--model", "nowhere.toml"], ["nowhere.toml", "model file not found"]),
    (["--model", "imu7"], ["imu7", "model file not found"]),
    (["--out", "no/such/folder/x.csv"], ["no/such/folder/x.csv", "--out", "does not exist"]),
])
def test_simulate_bad_arguments(capsys, tmp_path, argv, fragments):
    args = {"--model": RTD2, "--profile": "shock", "--out": str(tmp_path / "x.csv")}
    args.update(dict(zip(argv[::2], argv[1::2])))
    rc, _, err = run(capsys, "simulate", *(x for kv in args.items() for x in kv))
    assert_user_error(rc, err, *fragments)


def test_simulate_bad_csv_subprocess(tmp_path):
    path = tmp_path / "gappy.csv"
    path.write_text("time_s,T_fluid\n0,20\n1,\n2,21\n")
    proc = run_process("simulate", "--model", "rtd2", "--profile", path,
                       "--out", tmp_path / "x.csv")
    assert_user_error(proc.returncode, proc.stderr, str(path), "line 3", "'T_fluid'")
    assert proc.stdout == ""


# ---------------------------------------------------------------------------
# bad model files through the command line

RTD2_TEXT = (CONFIGS / "rtd2.toml").read_text()


def _line_of(text, needle, index=0):
    """1-based line of the `index`-th line of `text` holding `needle`."""
    return [k for k, line in enumerate(text.splitlines(), start=1) if needle in line][index]


BAD_MODELS = [
    ("unknown-node", lambda t: t.replace('between = ["sheath", "core"]',
                                         'between = ["sheath", "kore"]'),
     ("[[links]]", 0), ["field 'links[0].between'", "unknown node 'kore'"]),
    ("zero-conductance", lambda t: t.replace("conductance = 0.2", "conductance = 0.0"),
     ("[[boundaries]]", 0), ["field 'boundaries[0].conductance'", "positive number of W/K"]),
    ("island", lambda t: t + '\n[[nodes]]\nname = "a"\ncapacitance = 1.0\n\n[[nodes]]\n'
                             'name = "b"\ncapacitance = 1.0\n\n[[links]]\nbetween = ["a", "b"]\n'
                             'conductance = 1.0\n',
     ("[[nodes]]", 2), ["field 'nodes[2].name'", "no conduction path to any boundary"]),
    ("syntax", lambda t: t.replace("capacitance = 0.1", "capacitance = 0.1.0"),
     ("capacitance = 0.1.0", 0), ["TOML syntax error", "Fix the syntax at that line"]),
    ("viscoelastic", lambda t: t + '\n[[effects]]\nkind = "viscoelastic"\n'
                                   'where = ["core", "gyro"]\n',
     ("[[effects]]", 0), ["field 'effects[0].where'", "[[biases]]"]),
    ("no-value", lambda t: t.replace("capacitance = 0.8", "capacitance = { fixed = true }"),
     ("[[nodes]]", 0), ["field 'nodes[0].capacitance'", "{ value = 0.8, fixed = true }"]),
    ("unknown-key", lambda t: t.replace('column = "T_core"', 'column = "T_core"\nunit = "C"'),
     ('unit = "C"', 0), ["field 'sensors[0].unit'", "unknown key 'unit'"]),
]


@pytest.mark.parametrize("edit,anchor,fragments", [m[1:] for m in BAD_MODELS],
                         ids=[m[0] for m in BAD_MODELS])
def test_simulate_bad_model(capsys, tmp_path, edit, anchor, fragments):
    text = edit(RTD2_TEXT)
    assert text != RTD2_TEXT
    path = tmp_path / "bad_model.toml"
    path.write_text(text)
    line = _line_of(text, *anchor)  # the offending entry's [[table]] header, or the bad line
    rc, _, err = run(capsys, "simulate", "--model", str(path), "--profile", "shock",
                     "--out", str(tmp_path / "x.csv"))
    assert_user_error(rc, err, str(path), f"line {line}", *fragments)


def test_simulate_bad_model_subprocess(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text(RTD2_TEXT.replace('name = "core"', 'name = "core'))
    proc = run_process("simulate", "--model", path, "--profile", "shock",
                       "--out", tmp_path / "x.csv")
    line = _line_of(RTD2_TEXT, 'name = "core"')
    assert_user_error(proc.returncode, proc.stderr, str(path), f"line {line}",
                      "TOML syntax error")


# ---------------------------------------------------------------------------
# demo


def test_demo(capsys, tmp_path):  # about 6 s: not `slow`
    out = tmp_path / "demo"
    rc, stdout, err = run(capsys, "demo", "--quick", "--out", str(out))
    assert rc == 0, err
    csv, png = out / "imu6_calibration.csv", out / "imu6_calibration.png"
    assert csv.is_file() and png.is_file()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    tel = read_telemetry(csv)
    spec = load_model(CONFIGS / "imu6.toml")
    for column in (*spec.input_columns, *spec.sensor_columns):
        assert column in tel.names
    # The schedule swings the chamber between its -40 and +85 °C plateaus.
    assert tel.column("T_chamber").min() == -40.0 and tel.column("T_chamber").max() == 85.0
    assert str(csv) in stdout and str(png) in stdout


# ---------------------------------------------------------------------------
# the API raises the same errors (InputError is a ValueError)


def _telemetry(tmp_path, text, name="run.csv"):
    path = tmp_path / name
    path.write_text(text)
    return read_telemetry(path)


def test_model_inputs_and_outputs(tmp_path):
    spec = load_model(RTD2)
    tel = _telemetry(tmp_path, "time_s,T_core,T_fluid\n0,20,21\n1,,22\n2,20.5,23\n")
    np.testing.assert_array_equal(io.model_inputs(spec, tel), [[21.0], [22.0], [23.0]])
    y = io.model_outputs(spec, tel)
    assert y.shape == (3, 1) and np.isnan(y[1, 0]) and y[2, 0] == 20.5  # dropped sample kept


def test_model_inputs_missing_column(tmp_path):
    spec = load_model(RTD2)
    tel = _telemetry(tmp_path, "time_s,T_core,T_air\n0,20,21\n1,20,22\n")
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 'run.csv'}, field 'T_fluid': "
                                                   "no column 'T_fluid'; the available columns "
                                                   "are: T_core, T_air")):
        io.model_inputs(spec, tel)


@pytest.mark.parametrize("cell", ["nan", "", "inf", "-inf"])
def test_model_inputs_non_finite(tmp_path, cell):
    spec = load_model(RTD2)
    tel = _telemetry(tmp_path, f"# header comment\ntime_s,T_fluid\n0,20\n1,{cell}\n2,21\n")
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'run.csv'}, line 4, field "
                                                   "'T_fluid': input column 'T_fluid' is empty "
                                                   "or not finite at line 4")):
        io.model_inputs(spec, tel)


def test_model_inputs_in_memory_names_the_row():
    spec = load_model(RTD2)
    tel = Telemetry(ts=[0.0, 1.0, 2.0], channels={"T_fluid": [20.0, 21.0, np.nan]})
    with pytest.raises(InputError, match=r"field 'T_fluid': .*at data row 3"):
        io.model_inputs(spec, tel)


def test_model_outputs_missing_sensor_column(tmp_path):
    spec = load_model(CONFIGS / "imu6.toml")
    tel = _telemetry(tmp_path, "time_s,T_chamber,P_asic,T_housing,T_asic\n"
                               "0,20,0,20,20\n1,20,0,20,20\n")
    io.model_inputs(spec, tel)  # the inputs are all there
    with pytest.raises(ValueError, match=re.escape(
            f"{tmp_path / 'run.csv'}, field 'T_pcb': no column 'T_pcb'; the available columns "
            "are: T_chamber, P_asic, T_housing, T_asic")):
        io.model_outputs(spec, tel)


def test_model_outputs_empty_sensor_column(tmp_path):
    spec = load_model(RTD2)
    tel = _telemetry(tmp_path, "time_s,T_fluid,T_core\n0,20,\n1,20,nan\n")
    with pytest.raises(InputError, match=r"run\.csv, field 'T_core': sensor column 'T_core' has "
                                         r"no readings"):
        io.model_outputs(spec, tel)


@pytest.mark.parametrize("text,fragment", [
    ("time_s,T_fluid\n0,1\n0,2\n", r"line 3, field 'time_s'.*strictly increasing"),
    ("time_s,T_fluid\n0,1\n1,x\n", r"line 3, field 'T_fluid': cell 'x'"),
    ("", r"no header"),
])
def test_read_telemetry_errors_are_value_errors(tmp_path, text, fragment):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*" + fragment):
        read_telemetry(path)


def test_load_profile(tmp_path):
    assert len(io.load_profile("shock")) == 4201
    with pytest.raises(InputError, match=r"nowhere\.csv, field '--profile': no such file"):
        io.load_profile(str(tmp_path / "nowhere.csv"))
    with pytest.raises(InputError, match=r"'sunrise' is neither a built-in profile"):
        io.load_profile("sunrise")
