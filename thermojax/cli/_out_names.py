"""An `--out` path that can name an output at all: refused before any work, with a message
naming it, where it is empty, `.` or `..`, a dangling symbolic link, or has a component
longer than the file system allows (255 bytes on most)."""

from __future__ import annotations

import os
from pathlib import Path

from .._errors import InputError

NAME_MAX = 255  # bytes of one path component, where the file system does not say


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder if folder.is_dir() else ".", "PC_NAME_MAX"))
    except (OSError, ValueError):
        return NAME_MAX


def check_out_name(path: Path, field: str = "--out", *, existing_folder: bool = False) -> None:
    """Refuse (`InputError`) an output path no command can write as its own.
    `existing_folder`: the command writes into a folder in place, so `.` or `..` that
    exists is a folder it may use."""
    text = str(path)
    if (text in ("", ".") or path.name in ("", ".", "..")) and not (
            existing_folder and text != "" and path.is_dir()):
        raise InputError("names no file or folder of its own (empty, '.' or '..'); give a "
                         "new name such as results/ or run.csv.", file=repr(text), field=field)
    limit = _name_max(path.parent)
    for part in path.parts:
        if len(os.fsencode(part)) > limit:
            raise InputError(f"a name in the path is {len(os.fsencode(part))} bytes long, more "
                             f"than the {limit} the file system allows; choose a shorter name.",
                             file=text[:80] + "...", field=field)
    if path.is_symlink() and not path.exists():
        raise InputError(f"is a symbolic link to '{os.readlink(path)}', which does not exist; "
                         "remove the link or choose another name.", file=text, field=field)
