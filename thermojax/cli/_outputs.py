"""Where a command may write: checked before any work, written whole or not at all.

A command never overwrites a file or folder it did not write itself unless given
`--force` (docs/formats.md §5). Folders a command writes carry a marker file, so a later run of
the same command may replace (or, for `investigate`, resume) them; a CSV written by
`simulate` or `resample` is recognized by its first comment line. Results are written into a hidden
temporary folder next to the target and renamed into place when complete, so an error
or Ctrl-C never leaves a half-filled folder where the results should be.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

from .._errors import InputError

MARKER = ".thermojax"
OWN_CSV_MARKS = ("simulated by thermojax", "written by thermojax")  # first comment line


def is_own_folder(path: Path) -> bool:
    return (path / MARKER).is_file()


def _is_own_csv(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            first = f.readline()
        return any(mark in first for mark in OWN_CSV_MARKS)
    except OSError:
        return False


def _check_parent(path: Path) -> None:
    parent = path.parent
    if not parent.is_dir():
        raise InputError(f"the folder '{parent}' does not exist; create it first or choose "
                         "another path.", file=str(path), field="--out")


def check_output_folder(path: Path, force: bool) -> None:
    """Refuse, before any work, an `--out` folder this command may not write."""
    _check_parent(path)
    if path.is_file():
        raise InputError("is a file, but --out names a folder for this command; choose a "
                         "folder name.", file=str(path), field="--out")
    if path.is_dir() and any(path.iterdir()) and not is_own_folder(path) and not force:
        raise InputError("the folder exists and was not written by thermojax; choose a new "
                         "folder, or pass --force to replace it.", file=str(path),
                         field="--out")


def check_output_file(path: Path, force: bool) -> None:
    """Refuse, before any work, an `--out` file this command may not write."""
    _check_parent(path)
    if path.is_dir():
        raise InputError("is a folder, but --out names a CSV file for this command; give a "
                         "file name such as run.csv.", file=str(path), field="--out")
    if path.exists() and not force and not _is_own_csv(path):
        raise InputError("the file exists and was not written by thermojax; "
                         "choose another name, or pass --force to replace it.",
                         file=str(path), field="--out")


def mark_own(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MARKER).write_text("written by thermojax; a later run may replace this folder\n")


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
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        path.rename(old)
        tmp.rename(path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(path)


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
