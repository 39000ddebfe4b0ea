"""A user's common mistakes on the command line: each gets a message naming the file or
flag and exit 2, before any work, and no file is lost; Ctrl-C exits 130 with finished
work kept and nothing half-written."""

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from thermojax.cli import main
from thermojax.measurements import read_telemetry

from helpers import CONFIGS, ROOT

RTD2 = str(CONFIGS / "rtd2.toml")


def run(capsys, *argv):
    capsys.readouterr()
    try:
        rc = main(list(map(str, argv)))
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_refused(rc, err, *fragments):
    assert rc == 2, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)


@pytest.fixture(scope="module")
def shock_csv(tmp_path_factory):
    """rtd2 through the shock profile with sensor noise: one small run to fit."""
    path = tmp_path_factory.mktemp("data") / "shock.csv"
    assert main(["simulate", "--model", RTD2, "--profile", "shock", "--out", str(path),
                 "--noise", "--seed", "1"]) == 0
    return path


def listing(folder):
    return sorted(p.name for p in folder.iterdir())


# ---------------------------------------------------------------------------
# simulate


def test_simulate_refuses_a_folder_as_out(capsys, tmp_path):
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                     "--out", tmp_path)
    assert_refused(rc, err, str(tmp_path), "--out", "is a folder")


def test_simulate_never_replaces_a_measured_file(capsys, tmp_path):
    measured = tmp_path / "mydata.csv"
    measured.write_text("time_s,T_core\n0,20.1\n1,20.2\n")
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                     "--out", measured)
    assert_refused(rc, err, str(measured), "--force")
    assert measured.read_text() == "time_s,T_core\n0,20.1\n1,20.2\n"
    assert listing(tmp_path) == ["mydata.csv"]  # no temporary file left behind
    rc, _, _ = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                   "--out", measured, "--force")
    assert rc == 0
    assert len(read_telemetry(measured)) == 4201


def test_simulate_may_replace_its_own_file(capsys, tmp_path):
    out = tmp_path / "sim.csv"
    for seed in ("1", "2"):
        rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                         "--out", out, "--noise", "--seed", seed)
        assert rc == 0, err
    assert "seed 2" in out.read_text().splitlines()[0]


@pytest.mark.parametrize("value, message", [("-1", "must be a positive number, got -1"),
                                            ("0", "must be a positive number, got 0"),
                                            ("nan", "must be a positive number"),
                                            ("abc", "expected a number")])
def test_simulate_bad_dt_names_the_flag(capsys, tmp_path, value, message):
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                     "--out", tmp_path / "x.csv", "--dt", value)
    assert_refused(rc, err, "--dt", message)
    assert listing(tmp_path) == []


def without_sensors(tmp_path):
    """rtd2 with its [[sensors]] table removed."""
    text = (CONFIGS / "rtd2.toml").read_text()
    path = tmp_path / "no_sensors.toml"
    path.write_text(text[:text.index("[[sensors]]")])
    return path


def test_simulate_model_without_sensors_writes_states_only_when_asked(capsys, tmp_path):
    model = without_sensors(tmp_path)
    out = tmp_path / "sim.csv"
    rc, _, err = run(capsys, "simulate", "--model", model, "--profile", "shock", "--out", out)
    assert_refused(rc, err, str(model), "no sensors", "[[sensors]]", "--states")
    assert not out.exists()
    rc, _, err = run(capsys, "simulate", "--model", model, "--profile", "shock", "--out", out,
                     "--states")
    assert rc == 0, err
    run_ = read_telemetry(out)
    assert set(run_.channels) == {"T_fluid", "state_sheath", "state_core"}
    assert len(run_) == 4201


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_simulate_non_finite_power_names_the_flag(capsys, tmp_path, value):
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                     "--out", tmp_path / "x.csv", "--power", value)
    assert_refused(rc, err, "--power", "must be a finite number")
    assert listing(tmp_path) == []


def test_simulate_non_finite_result_is_not_written(capsys, tmp_path):
    """A capacitance of 1e-100 J/K: a time constant of 1e-99 s at 1 s samples overflows
    the sampled model; the file of empty cells it used to write is refused."""
    model = tmp_path / "tiny.toml"
    model.write_text((CONFIGS / "rtd2.toml").read_text().replace(
        "capacitance = 0.1\n", "capacitance = 1e-100\n"))
    out = tmp_path / "sim.csv"
    rc, _, err = run(capsys, "simulate", "--model", model, "--profile", "shock", "--out", out)
    assert_refused(rc, err, str(model), "node 'core'", "not finite", "time constant",
                   "sample period", "Nothing was written")
    assert listing(tmp_path) == ["tiny.toml"]


def test_simulate_missing_output_folder(capsys, tmp_path):
    rc, _, err = run(capsys, "simulate", "--model", RTD2, "--profile", "shock",
                     "--out", tmp_path / "nope" / "x.csv")
    assert_refused(rc, err, "does not exist", "--out")


# ---------------------------------------------------------------------------
# fit: arguments checked before the work


@pytest.mark.parametrize("argv, fragments", [
    (["--profile", "BADNAME"], ["'BADNAME' is not a free parameter", "--profile",
                                "links.sheath-core.conductance"]),
    (["--profile", "nodes.core.capacitance", "--likelihood", "kalman"],
     ["output-error fits only", "--profile"]),
    (["--starts", "0"], ["--starts", "must be at least 1"]),
    (["--starts", "two"], ["--starts", "expected a whole number"]),
])
def test_fit_arguments_refused_before_work(capsys, monkeypatch, tmp_path, shock_csv, argv,
                                           fragments):
    import thermojax.fitting._fit as fit_module

    def no_fit(*args, **kwargs):
        raise AssertionError("the fit ran before the arguments were checked")

    monkeypatch.setattr(fit_module, "fit", no_fit)
    out = tmp_path / "fit"
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out, *argv)
    assert_refused(rc, err, *fragments)
    assert not out.exists()


def test_fit_refuses_a_foreign_folder_and_keeps_it(capsys, tmp_path, shock_csv):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(out), "--force", "not written by thermojax")
    assert listing(out) == ["mine.txt"]


def test_fit_refuses_a_file_as_out(capsys, tmp_path, shock_csv):
    out = tmp_path / "result"
    out.write_text("a file")
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(out), "is a file")
    assert out.read_text() == "a file"


@pytest.mark.slow
def test_fit_replaces_its_own_folder_whole(capsys, tmp_path, shock_csv):
    out = tmp_path / "fit"
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert rc == 0, err
    (out / "stale.txt").write_text("from an earlier run")
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert rc == 0, err
    assert "stale.txt" not in listing(out)  # replaced whole, not merged
    assert {"model.toml", "report.json"} <= set(listing(out))
    assert [p for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_missing_data_file_is_named(capsys, tmp_path):
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", tmp_path / "nope.csv",
                     "--out", tmp_path / "fit")
    assert_refused(rc, err, "nope.csv")
    assert not (tmp_path / "fit").exists()


def test_fit_model_without_sensors_names_the_model_file(capsys, tmp_path, shock_csv):
    model = without_sensors(tmp_path)
    out = tmp_path / "fit"
    rc, _, err = run(capsys, "fit", "--model", model, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(model), "no sensors", "add a [[sensors]] table")
    assert not out.exists()


@pytest.mark.parametrize("command", ["diagnose", "investigate"])
def test_loop_commands_refuse_foreign_folder(capsys, tmp_path, shock_csv, command):
    out = tmp_path / "work"
    out.mkdir()
    (out / "thesis.tex").write_text("x")
    rc, _, err = run(capsys, command, "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(out), "--force")
    assert listing(out) == ["thesis.tex"]


def test_investigate_negative_max_steps(capsys, tmp_path, shock_csv):
    rc, _, err = run(capsys, "investigate", "--model", RTD2, "--data", shock_csv,
                     "--out", tmp_path / "inv", "--max-steps", "-1")
    assert_refused(rc, err, "--max-steps", "must be 0 or more")


# ---------------------------------------------------------------------------
# resample


def test_resample_refuses_a_huge_grid_before_allocating(capsys, tmp_path, shock_csv):
    out = tmp_path / "fine.csv"
    rc, _, err = run(capsys, "resample", "--data", shock_csv, "--out", out, "--dt", "1e-9")
    assert_refused(rc, err, str(shock_csv), "--dt", "4,200,000,000,005 samples",
                   "limit of 50,000,000")
    assert not out.exists()


# ---------------------------------------------------------------------------
# export


@pytest.mark.parametrize("value", ["nan", "inf", "-300"])
def test_export_refuses_an_impossible_operating_point(capsys, tmp_path, value):
    model = ROOT / "thermojax" / "data" / "chain3_truth.toml"  # nonlinear: linearized at it
    out = tmp_path / "obs"
    rc, _, err = run(capsys, "export", "--model", model, "--rate", "10", "--out", out,
                     "--operating-point", value)
    assert_refused(rc, err, "--operating-point", "absolute zero")
    assert not out.exists()


def test_export_implausibly_high_rate_names_the_rate(capsys, tmp_path):
    """At 1 GHz the imu6 observer's sampled matrices are the identity to within 1e-8:
    the rate is at fault, not the sensors (which observe every state at 100 Hz)."""
    out = tmp_path / "obs"
    rc, _, err = run(capsys, "export", "--model", "imu6", "--rate", "1e9", "--out", out)
    assert_refused(rc, err, "--rate", "implausibly high", "lower --rate")
    assert "--sensor" not in err
    assert not out.exists()


# ---------------------------------------------------------------------------
# Ctrl-C


def interrupt_after(argv, seconds, tmp_path, until=None, after_line=None):
    """Start `thermojax argv...` as a real process and send SIGINT after `seconds`, or
    sooner: as soon as the file `until` appears, or a second after the command prints a
    line containing `after_line` (its work under way: a fixed delay raced the end of a
    fit that a warm compilation cache makes short). Returns `(rc, stdout, stderr)`."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.Popen([sys.executable, "-m", "thermojax", *map(str, argv)], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err, started = [], [], threading.Event()

    def read(stream, into, watch):
        for line in stream:
            into.append(line)
            if watch is not None and watch in line:
                started.set()

    readers = [threading.Thread(target=read, args=(proc.stdout, out, after_line), daemon=True),
               threading.Thread(target=read, args=(proc.stderr, err, None), daemon=True)]
    for r in readers:
        r.start()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (until is not None and until.is_file()) \
            and not started.is_set():
        time.sleep(0.2)
    if started.is_set():
        time.sleep(1.0)
    assert proc.poll() is None, ("".join(out), "".join(err))  # still working when interrupted
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=120)
    for r in readers:
        r.join(timeout=10)
    proc.stdout.close()
    proc.stderr.close()
    return proc.returncode, "".join(out), "".join(err)


@pytest.mark.parametrize("command, says, not_says", [
    ("fit", "nothing was written", "resume"),
    ("montecarlo", "--resume", "investigation"),
    ("investigate", "resumes after the last", "nothing was written"),
])
def test_interrupted_message_matches_the_command(command, says, not_says):
    from thermojax.cli._main import interrupted_message

    message = interrupted_message(command)
    assert message.startswith(f"thermojax {command}: interrupted; ")
    assert says in message and not_says not in message


@pytest.mark.slow
def test_ctrl_c_during_fit_exits_130_and_writes_nothing(tmp_path, shock_csv):
    out = tmp_path / "fit"
    # interrupted a second into the fit (10-15 s of work after the first message)
    rc, _, err = interrupt_after(["fit", "--model", RTD2, "--data", shock_csv, "--out", out,
                                  "--likelihood", "kalman"], 60, tmp_path,
                                 after_line="fitting 1 run(s)")
    assert rc == 130, err
    assert "Traceback" not in err and "interrupted" in err
    assert not out.exists()
    assert [p for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_ctrl_c_during_investigate_exits_130_and_resumes(tmp_path):
    """The chain3 demo data, cut to their first 1500 samples: step 0 takes a few seconds
    after compilation and the first added effect about a minute; an interrupt keeps the
    finished steps and a rerun resumes from them."""
    from thermojax.cli import demo_runs
    from thermojax.measurements import write_telemetry

    n = 1500
    paths = []
    for i, (ts, columns) in enumerate(demo_runs()):
        paths.append(write_telemetry(tmp_path / f"run{i}.csv", ts[:n],
                                     {k: v[:n] for k, v in columns.items()}))
    model = ROOT / "thermojax" / "data" / "chain3.toml"
    out = tmp_path / "inv"
    argv = ["investigate", "--model", model, *sum((["--data", p] for p in paths), []),
            "--out", out, "--max-steps", "1"]
    # interrupted as soon as step 1 is checkpointed (while the report and plots are written)
    # (a generous deadline: on a loaded machine step 1 took over 300 s)
    rc, _, err = interrupt_after(argv, 900, tmp_path, until=out / "checkpoint.json")
    assert rc == 130, err
    assert "Traceback" not in err and "interrupted" in err
    assert (out / ".thermojax").is_file()
    finished = (out / "checkpoint.json").is_file()
    assert finished
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-m", "thermojax", *map(str, argv)], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    assert ("resuming after step" in proc.stdout) == finished
    assert (out / "report.json").is_file() and (out / "model_final.toml").is_file()


# ---------------------------------------------------------------------------
# progress


@pytest.mark.slow
def test_progress_plain_when_not_a_terminal_and_silent_when_quiet(capsys, tmp_path, shock_csv):
    rc, out, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv,
                       "--out", tmp_path / "a")
    assert rc == 0, err
    assert "  fitting 1 run(s) under the output_error likelihood" in out
    assert "\x1b[" not in out  # no terminal control codes in a log file
    rc, out_quiet, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv,
                             "--out", tmp_path / "b", "--quiet")
    assert rc == 0, err
    assert "fitting 1 run(s)" not in out_quiet and "output error pass" not in out_quiet
    assert "RMSE" in out_quiet  # the results are still printed


# ---------------------------------------------------------------------------
# compilation cache


@pytest.mark.slow
def test_compilation_cache_is_written_reused_and_can_be_turned_off(tmp_path, shock_csv):
    cache = tmp_path / "cache"

    def fit(out, *extra):
        env = dict(os.environ, JAX_PLATFORMS="cpu", THERMOJAX_CACHE_DIR=str(cache))
        proc = subprocess.run([sys.executable, "-m", "thermojax", "fit", "--model", RTD2,
                               "--data", str(shock_csv), "--out", str(tmp_path / out),
                               "--quiet", *extra], env=env, capture_output=True, text=True,
                              timeout=600)
        assert proc.returncode == 0, proc.stderr
        return (tmp_path / out / "model.toml").read_text()

    no_cache = fit("a", "--no-cache")
    assert not cache.exists()
    first = fit("b")
    (folder,) = cache.iterdir()
    assert folder.name.startswith("jax-")  # one folder per JAX version
    entries = sorted(p.name for p in folder.iterdir())
    assert entries
    second = fit("c")
    assert sorted(p.name for p in folder.iterdir()) == entries  # all read back, none new
    assert first == second == no_cache  # the same fitted model either way
