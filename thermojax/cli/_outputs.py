"""Where a command may write: checked before any work, written whole or not at all.

A command never overwrites a file or folder it did not write itself unless given
`--force` (docs/formats.md §5, docs/cli.md "Existing files and folders"). Folders a
command writes carry a marker file `.thermojax` naming the command, so a later run of the
same command may replace (or, for `investigate` and `montecarlo`, resume) them, while a
folder of another command is refused without `--force`; a CSV written by `simulate` or
`resample` is recognized by its first comment line. Results are written into a hidden
temporary folder next to the target and renamed into place when complete, so an error
or Ctrl-C never leaves a half-filled folder where the results should be.

Within a command-line run (`output_session`, opened by `main`), checking an output also
claims it: an exclusive lock beside it (`.NAME.lock` in its folder) held until the command
ends, so a second run onto the same output is refused at once; a probe that the location
is writable and has room; and the removal of temporary files and folders a dead run left
there (`.NAME.partial-*`, `.NAME.old-*`: no live run writes them, it would hold the lock).
A write that fails on the way (disk full, read-only, permission) ends the command with a
message naming the path and exit 2, never a traceback, and no partial folder is left.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import glob
import json
import os
import shutil
import tempfile
from pathlib import Path

from .._errors import InputError

MARKER = ".thermojax"
OWN_CSV_MARKS = ("simulated by thermojax", "written by thermojax")  # first comment line
ROOM_FOLDER = 1 << 20  # bytes: the least any folder a command writes takes (reports, plots)
ROOM_FILE = 16 << 10  # bytes: the least a CSV a command writes takes
WRITE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG,
                getattr(errno, "EDQUOT", errno.ENOSPC)}

# What each command's folder holds, in the words of a refusal (legacy markers: inferred).
_HOLDS = {"montecarlo": "its chunks and manifest", "investigate": "its steps and checkpoint",
          "fit": "a fitted model and its report", "diagnose": "a diagnosis report",
          "calibrate": "calibration results", "export": "an exported observer",
          "demo": "the demo's files"}


def is_own_folder(path: Path) -> bool:
    return (path / MARKER).is_file()


def folder_command(path: Path) -> str | None:
    """The command that wrote the thermojax folder `path`: the marker's `command`, or for a
    marker of an earlier version (plain text) what the folder holds; None when unknown."""
    try:
        command = json.loads((path / MARKER).read_text()).get("command")
    except (OSError, ValueError, AttributeError):
        command = None
    if command:
        return str(command)
    if (path / "manifest.json").is_file() and (path / "chunks").is_dir():
        return "montecarlo"
    if (path / "checkpoint.json").is_file() or any(path.glob("step*_model.toml")):
        return "investigate"
    return None


def _is_own_csv(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            first = f.readline()
        return any(mark in first for mark in OWN_CSV_MARKS)
    except OSError:
        return False


def _check_parent(path: Path, *, existing_folder: bool = False) -> None:
    from ._out_names import check_out_name

    check_out_name(path, existing_folder=existing_folder)
    parent = path.parent
    if not parent.is_dir():
        raise InputError(f"the folder '{parent}' does not exist; create it first or choose "
                         "another path.", file=str(path), field="--out")


# ---------------------------------------------------------------------------
# the session: locks held while one command runs, write errors made messages


class _Session:
    def __init__(self, command: str | None):
        self.command = command
        self.locks: dict[Path, _Lock] = {}
        self.claimed: list[tuple[Path, bool]] = []  # (output, written in place)

    def release(self) -> None:
        for lock in reversed(list(self.locks.values())):
            lock.release()
        self.locks.clear()


_session: _Session | None = None


@contextlib.contextmanager
def output_session(command: str | None):
    """Hold the outputs the command claims (`check_output_folder`, `check_output_file`)
    until it ends; turn a failed write (disk full, read-only, permission) into an
    `InputError` naming the path. Opened by `thermojax.cli.main` around each command."""
    global _session
    previous, _session = _session, _Session(command)
    session = _session
    try:
        yield session
    except OSError as err:
        if err.errno not in WRITE_ERRNOS:
            raise
        raise _write_error(err, session) from None
    finally:
        _session = previous
        session.release()


def _write_error(err: OSError, session: _Session) -> InputError:
    path = err.filename or (str(session.claimed[-1][0]) if session.claimed else None)
    for out, _ in session.claimed:  # a file in a staged folder: name the output instead
        if path is not None and os.fspath(path).startswith(
                os.fspath(out.parent / f".{out.name}.partial-")):
            path = out
    if err.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG):
        fix = "free some space, or choose an --out on another disk"
    elif err.errno == errno.EROFS:
        fix = "the file system is read-only: choose an --out on a writable disk"
    else:
        fix = ("check the permissions of the file and its folder, or choose an --out you may "
               "write to")
    if any(in_place for _, in_place in session.claimed):
        kept = ("what was finished before the error is kept in the output folder; run the "
                "command again once the problem is fixed")
    elif session.claimed:
        kept = "nothing was put in place: the output is as it was before this run"
    else:
        kept = "what was written before the error is kept"
    return InputError(f"could not write ({err.strerror or err}); {fix}. {kept.capitalize()}.",
                      file=str(path) if path else None)


class _Lock:
    """An exclusive, non-blocking lock on the file `path` (created, removed on release).
    POSIX: `flock`, the holder's pid and command written into the file; elsewhere
    `filelock`."""

    def __init__(self, path: Path):
        self.path = path
        self.fd: int | None = None
        self.other = None

    def acquire(self, command: str | None) -> dict | None:
        """Take the lock; return None, or the holder's record when another run holds it."""
        try:
            import fcntl
        except ImportError:  # pragma: no cover (Windows)
            import filelock

            self.other = filelock.FileLock(str(self.path), timeout=0)
            try:
                self.other.acquire()
            except filelock.Timeout:
                self.other = None
                return {}
            return None
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except PermissionError:  # another account's lock file: flock needs no write
                if not self.path.exists():
                    raise
                fd = os.open(self.path, os.O_RDONLY)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_holder(fd)
                os.close(fd)
                return holder
            except BaseException:
                os.close(fd)
                raise
            try:  # the holder before us may have removed the file we opened: try again
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            with contextlib.suppress(OSError):  # the holder's record, for a refused run
                os.ftruncate(fd, 0)
                os.write(fd, json.dumps({
                    "pid": os.getpid(), "command": command, "since": _dt.datetime.now(
                        _dt.timezone.utc).strftime("%H:%M:%S UTC")}).encode())
            self.fd = fd
            return None

    def release(self) -> None:
        if self.other is not None:  # pragma: no cover (Windows)
            self.other.release()
            self.other = None
        if self.fd is None:
            return
        import fcntl

        with contextlib.suppress(OSError):
            self.path.unlink()  # while still held: a waiter that opened it retries
        fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)
        self.fd = None


def _read_holder(fd: int) -> dict:
    try:
        return json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}


def lock_path(path: Path) -> Path:
    """The lock file of the output `path`: `.NAME.lock` in the same folder."""
    return path.parent / f".{path.name}.lock"


@contextlib.contextmanager
def output_lock(path: Path, command: str | None = None, *, key: str = ""):
    """Hold the exclusive lock of the output `path` (`InputError` if another run holds it)."""
    lock = _take_lock(Path(path), command, key)
    try:
        yield lock
    finally:
        lock.release()


def _take_lock(path: Path, command: str | None, key: str = "") -> _Lock:
    lock = _Lock(lock_path(path) if not key else path.parent / f".{path.name}.{key}.lock")
    try:
        holder = lock.acquire(command)
    except OSError as err:
        raise _not_writable(path.parent, path, err) from None
    if holder is not None:
        who = ", ".join(x for x in (
            f"`thermojax {holder['command']}`" if holder.get("command") else "",
            f"pid {holder['pid']}" if holder.get("pid") else "",
            f"since {holder['since']}" if holder.get("since") else "") if x)
        raise InputError(f"another thermojax run ({who or 'pid unknown'}) is writing this "
                         "output; wait for it to finish, or choose another --out. Two runs "
                         "onto one output would leave only the last one's results.",
                         file=str(path), field="--out")
    return lock


def _not_writable(folder: Path, path: Path, err: OSError) -> InputError:
    return InputError(f"cannot write in the folder '{folder}' ({err.strerror or err}); "
                      "nothing was done. Choose an --out you may write to"
                      + (" (the file system is read-only)" if err.errno == errno.EROFS else
                         ", or fix the folder's permissions") + ".",
                      file=str(path), field="--out")


def _probe_writable(folder: Path, path: Path) -> None:
    """Create and remove a file in `folder`: an `InputError` now rather than after the work."""
    probe = folder / f".thermojax-probe-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise _not_writable(folder, path, err) from None


def check_room(path: Path, need: int) -> None:
    """Refuse, before any work, an output on a disk with less than `need` bytes free."""
    folder = path if path.is_dir() else path.parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return  # cannot tell: the writes themselves will say
    if free < need:
        raise InputError(f"the disk holding '{folder}' has {_size(free)} free, and this "
                         f"command writes at least {_size(need)}; free some space, or "
                         "choose an --out on another disk. Nothing was done.",
                         file=str(path), field="--out")


def _size(n: int) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} bytes"  # pragma: no cover


def remove_stale(path: Path) -> list[Path]:
    """Remove what a dead run left beside `path` (`.NAME.partial-*`, `.NAME.old-*`) and,
    in a thermojax folder, its half-written files (`.*.partial-*`, `*.tmp`). Call only
    while holding `path`'s lock: a live run writing them would hold it."""
    removed = []
    name = glob.escape(path.name)
    for p in [*path.parent.glob(f".{name}.partial-*"), *path.parent.glob(f".{name}.old-*")]:
        if p.is_dir() and not p.is_symlink():
            if ".partial-" in p.name and not is_own_folder(p) and any(p.iterdir()):
                continue  # not a folder thermojax staged (each gets its marker first)
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    if path.is_dir() and is_own_folder(path):
        for p in [*path.glob(".*.partial-*"), *path.glob("*.json.tmp")]:
            if p.is_file():
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


def _claim(path: Path, room: int, in_place: bool, shared: str | None) -> None:
    """Within a session: lock `path`, check it is writable and has room, clean what a dead
    run left. Outside one (the library called from Python): the writable and room checks."""
    session = _session
    if session is not None and path not in session.locks:
        session.locks[path] = _take_lock(path, session.command, key=shared or "")
        session.claimed.append((path, in_place))
        if shared is None:
            remove_stale(path)
    else:
        _probe_writable(path.parent, path)
    if in_place and path.is_dir():
        _probe_writable(path, path)
    check_room(path, room)


def claim_output_folder(path: Path) -> None:
    """Lock a folder the command fills beside what it holds (`calibrate
    --make-example-data DIR`), and check it is writable and has room, before any work,
    without judging what the folder already holds (nothing in it is removed)."""
    _check_parent(path, existing_folder=True)
    if path.is_file():
        raise InputError("is a file, but this names a folder; choose a folder name.",
                         file=str(path))
    _claim(path, ROOM_FOLDER, True, None)


def _current_command() -> str | None:
    return _session.command if _session is not None else None


def check_output_folder(path: Path, force: bool, *, in_place: bool = False,
                        shared: str | None = None) -> None:
    """Refuse, before any work, an `--out` folder this command may not write; claim it.

    A folder not written by thermojax, or written by another command (its marker), is
    refused unless `force`. `in_place`: the command writes into the folder itself
    (`investigate`, `montecarlo`, `demo`) rather than replacing it whole, so with `force` a
    folder that is not its own is emptied first, and its own folder is kept for it to
    resume. `shared`: several processes fill one folder (a sharded Monte Carlo study),
    each holding a lock of its own under this key.
    """
    _check_parent(path)
    if path.is_file():
        raise InputError("is a file, but --out names a folder for this command; choose a "
                         "folder name.", file=str(path), field="--out")
    _claim(path, ROOM_FOLDER, in_place, shared)
    if not (path.is_dir() and any(path.iterdir())):
        return
    command = _current_command()
    if not is_own_folder(path):
        if not force:
            raise InputError("the folder exists and was not written by thermojax; choose a "
                             "new folder, or pass --force to replace it.", file=str(path),
                             field="--out")
        if in_place:
            _empty(path)
        return
    by = folder_command(path)
    if by is None or command is None or by == command:
        return
    if not force:
        raise InputError(f"the folder was written by `thermojax {by}` and holds "
                         f"{_HOLDS.get(by, 'its results')}; `thermojax {command}` would "
                         "replace it. Choose another --out, or pass --force to replace it.",
                         file=str(path), field="--out")
    if in_place:
        _empty(path)


def _empty(path: Path) -> None:
    """Remove everything in the folder `path` (`--force` onto a folder not the command's)."""
    for p in path.iterdir():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def check_output_file(path: Path, force: bool) -> None:
    """Refuse, before any work, an `--out` file this command may not write; claim it."""
    _check_parent(path)
    if path.is_dir():
        raise InputError("is a folder, but --out names a CSV file for this command; give a "
                         "file name such as run.csv.", file=str(path), field="--out")
    _claim(path, ROOM_FILE, False, None)
    if path.exists() and not force and not _is_own_csv(path):
        raise InputError("the file exists and was not written by thermojax; "
                         "choose another name, or pass --force to replace it.",
                         file=str(path), field="--out")


def mark_own(folder: Path, command: str | None = None) -> None:
    """Write the marker `.thermojax` into `folder`: JSON naming the command (the session's
    when not given), so a later run of it may replace the folder and others refuse it."""
    folder.mkdir(parents=True, exist_ok=True)
    command = command or _current_command()
    (folder / MARKER).write_text(json.dumps({
        "written_by": "thermojax", "command": command, "version": _version(),
        "note": "a later run of the same command may replace this folder"}, indent=1) + "\n")


def _version() -> str:
    try:
        from .. import __version__
        return str(__version__)
    except ImportError:  # pragma: no cover
        return "unknown"


@contextlib.contextmanager
def staged_folder(path: Path):
    """Yield a temporary folder beside `path`; on success it replaces `path` whole.

    On an error or Ctrl-C the temporary folder is removed and `path` is untouched.
    """
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-", dir=path.parent))
    tmp.chmod(0o777 & ~_umask())  # mkdtemp makes it private; results are ordinary files
    try:
        mark_own(tmp)
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            path.rename(old)
            try:
                tmp.rename(path)
            except BaseException:
                old.rename(path)  # the earlier results back in place
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def staged_file(path: Path):
    """Yield a temporary file path beside `path`; on success it replaces `path`."""
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.partial-", suffix=path.suffix,
                                dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    tmp.chmod(0o666 & ~_umask())
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
