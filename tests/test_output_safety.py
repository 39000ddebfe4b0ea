"""Output safety (issue 32, item 2): concurrent writers, folders of another command,
read-only and full outputs, leftovers of a dead run. Each refusal is exit 2 with the path
named and no traceback, before any work; nothing half-written is left behind.

Cheap by design: `simulate` on rtd2 at a 10 s period, `fit` with the fit itself stubbed
(each refusal comes before it), `investigate` and `montecarlo` folders faked by their
marker and files rather than made by a run."""

import collections
import errno
import json
import os
import subprocess
import sys

import pytest

from thermojax.cli import main
from thermojax.cli import _outputs
from thermojax.cli._outputs import output_lock, output_session

from helpers import CONFIGS
from helpers import run_cli as run, assert_refused

RTD2 = str(CONFIGS / "rtd2.toml")


def simulate(capsys, out, *extra):
    return run(capsys, "simulate", "--model", RTD2, "--profile", "shock", "--dt", "10",
               "--out", out, *extra)


def hidden(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def listing(folder):
    return sorted(p.name for p in folder.iterdir())


@pytest.fixture(scope="module")
def shock_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "shock.csv"
    assert main(["simulate", "--model", RTD2, "--profile", "shock", "--dt", "10",
                 "--out", str(path), "--noise", "--seed", "1"]) == 0
    return path


@pytest.fixture
def no_fit(monkeypatch):
    """`fit` must never get this far in these tests."""
    import thermojax.fitting._fit as fit_module

    def fail(*args, **kwargs):
        raise AssertionError("the fit ran although the output was refused")

    monkeypatch.setattr(fit_module, "fit", fail)


@pytest.fixture
def no_simulation(monkeypatch):
    import thermojax.cli._main as cli_main

    def fail(*args, **kwargs):
        raise AssertionError("the simulation ran although the output was refused")

    monkeypatch.setattr(cli_main, "_simulate_to_csv", fail)


def fake_folder(path, command, files):
    """A folder as `thermojax COMMAND` leaves it: the marker (JSON, or the plain text of
    earlier versions when `command` is None) and `files`."""
    path.mkdir()
    marker = ("written by thermojax; a later run may replace this folder\n" if command is None
              else json.dumps({"written_by": "thermojax", "command": command}))
    (path / ".thermojax").write_text(marker)
    for name, text in files.items():
        (path / name).parent.mkdir(parents=True, exist_ok=True)
        (path / name).write_text(text)
    return {name: text for name, text in files.items()}


MONTECARLO = {"manifest.json": "{}", "chunks/chunk_00000.npz": "data",
              "chunks/chunk_00000.json": "{}"}
INVESTIGATION = {"checkpoint.json": "{}", "step0_model.toml": "# model",
                 "report.json": "{}"}


# ---------------------------------------------------------------------------
# one writer per output


def test_a_run_onto_an_output_another_process_writes_is_refused(capsys, tmp_path,
                                                                no_simulation):
    out = tmp_path / "sim.csv"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from pathlib import Path; "
         "from thermojax.cli._outputs import output_lock\n"
         "with output_lock(Path(sys.argv[1]), 'simulate'):\n"
         "    print('locked', flush=True); sys.stdin.read()", str(out)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        rc, _, err = simulate(capsys, out)
        assert_refused(rc, err, str(out), "another thermojax run", f"pid {holder.pid}",
                       "`thermojax simulate`", "--out")
        assert (tmp_path / ".sim.csv.lock").exists()  # the holder's lock is left alone
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
        holder.stdout.close()
    assert listing(tmp_path) == []  # the holder removed its lock; nothing else was written


def test_a_second_fit_onto_a_locked_folder_is_refused_before_the_work(capsys, tmp_path,
                                                                      shock_csv, no_fit):
    out = tmp_path / "fit"
    with output_lock(out, "fit"):
        rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(out), "another thermojax run", f"pid {os.getpid()}")
    assert listing(tmp_path) == []


def test_the_lock_is_released_and_removed_after_a_run(capsys, tmp_path):
    out = tmp_path / "sim.csv"
    for _ in range(2):  # the second run is not refused by the first one's lock
        rc, _, err = simulate(capsys, out)
        assert rc == 0, err
    assert listing(tmp_path) == ["sim.csv"]


def test_sharded_montecarlo_processes_hold_locks_of_their_own(monkeypatch, tmp_path):
    from thermojax.cli._montecarlo import _shared_lock_key

    monkeypatch.delenv("THERMOJAX_PROCESS_INDEX", raising=False)
    monkeypatch.delenv("THERMOJAX_PROCESS_COUNT", raising=False)
    assert _shared_lock_key() is None or os.environ.get("JAX_COORDINATOR_ADDRESS")
    monkeypatch.setenv("THERMOJAX_PROCESS_COUNT", "2")
    monkeypatch.setenv("THERMOJAX_PROCESS_INDEX", "1")
    assert _shared_lock_key() == "process1"
    out = tmp_path / "mc"
    with output_lock(out, "montecarlo", key="process0"):
        with output_session("montecarlo"):  # process 1 shares the folder with process 0
            _outputs.check_output_folder(out, False, in_place=True, shared="process1")
        with output_session("montecarlo"), pytest.raises(ValueError, match="another thermojax"):
            _outputs.check_output_folder(out, False, in_place=True, shared="process0")


# ---------------------------------------------------------------------------
# folders of another command


@pytest.mark.parametrize("command, files", [
    ("montecarlo", MONTECARLO), (None, MONTECARLO),  # None: a marker of an earlier version
    ("investigate", INVESTIGATION), (None, INVESTIGATION)])
def test_fit_refuses_a_folder_of_another_command(capsys, tmp_path, shock_csv, no_fit,
                                                 command, files):
    out = tmp_path / "study"
    kept = fake_folder(out, command, files)
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    by = command or ("montecarlo" if "manifest.json" in files else "investigate")
    assert_refused(rc, err, str(out), f"written by `thermojax {by}`", "--force")
    for name, text in kept.items():
        assert (out / name).read_text() == text
    assert hidden(tmp_path) == []


@pytest.mark.parametrize("command", ["diagnose", "investigate"])
def test_loop_commands_refuse_a_montecarlo_folder(capsys, tmp_path, shock_csv, command):
    out = tmp_path / "study"
    kept = fake_folder(out, "montecarlo", MONTECARLO)
    rc, _, err = run(capsys, command, "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(out), "written by `thermojax montecarlo`", "--force")
    assert all((out / n).read_text() == t for n, t in kept.items())


def test_investigate_with_force_replaces_a_fit_folder(capsys, monkeypatch, tmp_path,
                                                      shock_csv):
    """Only with --force, and then nothing of the fit is left beside the investigation."""
    import thermojax.investigation._investigate as inv

    def fake_investigate(spec, runs, *, out, **kwargs):
        (out / "report.json").write_text("{}")
        return {"steps": [], "stopped_because": "max_steps"}

    monkeypatch.setattr(inv, "investigate", fake_investigate)
    out = tmp_path / "fit"
    fake_folder(out, "fit", {"model.toml": "# fitted", "report.json": "{\"fit\": 1}"})
    argv = ["investigate", "--model", RTD2, "--data", shock_csv, "--out", out]
    rc, _, err = run(capsys, *argv)
    assert_refused(rc, err, "written by `thermojax fit`", "--force")
    assert (out / "model.toml").is_file()
    rc, _, err = run(capsys, *argv, "--force")
    assert rc == 0, err
    assert listing(out) == [".thermojax", "report.json"]
    assert _outputs.folder_command(out) == "investigate"


def test_a_command_accepts_its_own_folder(tmp_path):
    out = tmp_path / "inv"
    fake_folder(out, "investigate", INVESTIGATION)
    with output_session("investigate"):
        _outputs.check_output_folder(out, False, in_place=True)
    assert (out / "checkpoint.json").is_file()  # kept for the command to resume


def test_the_marker_names_the_command(capsys, tmp_path):
    with output_session("fit"):
        _outputs.mark_own(tmp_path)
    doc = json.loads((tmp_path / ".thermojax").read_text())
    assert doc["command"] == "fit" and doc["written_by"] == "thermojax"


# ---------------------------------------------------------------------------
# read-only and full outputs


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only (chmod) folder "
                    "anyway; the monkeypatched read-only test below covers root")
def test_a_read_only_folder_is_refused_before_the_work(capsys, tmp_path, shock_csv, no_fit):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv,
                         "--out", folder / "fit")
        assert_refused(rc, err, str(folder / "fit"), "cannot write in the folder",
                       "Permission denied")
    finally:
        folder.chmod(0o755)


@pytest.fixture
def read_only(monkeypatch, tmp_path):
    """Writes under tmp_path/ro fail with EROFS, as on a read-only mount (works as root)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    real_open = os.open

    def fake_open(path, flags, *args, **kwargs):
        writes = flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)
        if writes and os.path.abspath(os.fspath(path)).startswith(str(folder)):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)
    return folder


@pytest.mark.parametrize("command", ["simulate", "fit"])
def test_a_read_only_disk_is_refused_before_the_work(capsys, read_only, shock_csv, no_fit,
                                                     no_simulation, command):
    if command == "simulate":
        out = read_only / "sim.csv"
        rc, _, err = simulate(capsys, out)
    else:
        out = read_only / "fit"
        rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, str(out), "cannot write in the folder", "read-only")
    assert listing(read_only) == []


def test_a_full_disk_is_refused_before_the_work(capsys, monkeypatch, tmp_path, shock_csv,
                                                no_fit, no_simulation):
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(_outputs.shutil, "disk_usage", lambda p: usage(10**9, 10**9, 512))
    rc, _, err = simulate(capsys, tmp_path / "sim.csv")
    assert_refused(rc, err, str(tmp_path / "sim.csv"), "512 bytes free", "free some space")
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv,
                     "--out", tmp_path / "fit")
    assert_refused(rc, err, str(tmp_path / "fit"), "at least 1.0 MiB")
    assert listing(tmp_path) == []


def disk_fills_up(path, *args, named=False, **kwargs):
    """A write that gets part way and then finds the disk full (with no file name, as a
    write(2) reports it, or `named`, as an open(2) does)."""
    with open(path, "w") as f:
        f.write("time_s,T\n0,1\n")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), *([str(path)] if named else []))


def test_a_disk_that_fills_during_simulate_leaves_the_earlier_file(capsys, monkeypatch,
                                                                   tmp_path):
    import thermojax.io as tio

    out = tmp_path / "sim.csv"
    rc, _, err = simulate(capsys, out)
    assert rc == 0, err
    before = out.read_text()
    monkeypatch.setattr(tio, "write_telemetry", disk_fills_up)
    rc, _, err = simulate(capsys, out, "--noise")
    assert_refused(rc, err, f"thermojax simulate: error: {out}: could not write",
                   os.strerror(errno.ENOSPC), "free some space", "Nothing was put in place")
    assert out.read_text() == before
    assert listing(tmp_path) == ["sim.csv"]  # no .partial file, no lock


def test_a_disk_that_fills_while_fit_writes_leaves_no_partial_folder(capsys, monkeypatch,
                                                                     tmp_path, shock_csv):
    import thermojax.fitting._fit as fit_module
    import thermojax.fitting._fit_report as report_module

    import types

    from thermojax import load_model

    # a fit that ends where it started: nothing to warn of, then the disk fills
    fitted = types.SimpleNamespace(likelihood="output_error", problem=None, dominant=[],
                                   nll=0.0, spec=load_model(RTD2))
    monkeypatch.setattr(fit_module, "fit", lambda *a, **k: fitted)

    def write_fit_outputs(result, experiments, folder, *args, **kwargs):
        disk_fills_up(folder / "model.toml", named=True)

    monkeypatch.setattr(report_module, "write_fit_outputs", write_fit_outputs)
    out = tmp_path / "fit"
    rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv, "--out", out)
    assert_refused(rc, err, f"error: {out}: could not write", os.strerror(errno.ENOSPC),
                   "Nothing was put in place")
    assert ".partial-" not in err  # the output is named, not its temporary folder
    assert listing(tmp_path) == []


# ---------------------------------------------------------------------------
# leftovers of a dead run


def test_a_dead_runs_partial_files_and_folders_are_removed(capsys, tmp_path):
    (tmp_path / ".sim.csv.partial-k3j2.csv").write_text("time_s\n0\n")
    staged = tmp_path / ".fit.partial-a8d1"
    staged.mkdir()
    (staged / ".thermojax").write_text("{}")
    (staged / "model.toml").write_text("# half")
    (tmp_path / ".fit.old-4242").mkdir()
    users = tmp_path / ".fit.partial-notes"  # not staged by thermojax: no marker
    users.mkdir()
    (users / "mine.txt").write_text("keep")
    rc, _, err = simulate(capsys, tmp_path / "sim.csv")
    assert rc == 0, err
    assert not (tmp_path / ".sim.csv.partial-k3j2.csv").exists()
    with output_session("fit"):
        _outputs.check_output_folder(tmp_path / "fit", False)
    assert hidden(tmp_path) == [".fit.partial-notes"]


def test_a_live_runs_partial_folder_is_left_alone(capsys, tmp_path, shock_csv, no_fit):
    staged = tmp_path / ".fit.partial-live"
    staged.mkdir()
    (staged / ".thermojax").write_text("{}")
    with output_lock(tmp_path / "fit", "fit"):
        rc, _, err = run(capsys, "fit", "--model", RTD2, "--data", shock_csv,
                         "--out", tmp_path / "fit")
        assert_refused(rc, err, "another thermojax run")
        assert staged.is_dir()


def test_half_written_files_in_a_resumable_folder_are_removed(tmp_path):
    out = tmp_path / "mc"
    fake_folder(out, "montecarlo", {**MONTECARLO, ".report.json.partial-x1": "{",
                                    "checkpoint.json.tmp": "{"})
    with output_session("montecarlo"):
        _outputs.check_output_folder(out, False, in_place=True)
    assert listing(out) == [".thermojax", "chunks", "manifest.json"]
