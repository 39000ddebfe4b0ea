"""A telemetry file read within a byte budget: its size checked before it is read (a
regular file), or counted while it is read (a pipe, a device such as `/dev/zero`), and
refused with the predicted memory when parsing it could not fit; a file of NUL bytes is
not text and is refused at its first block."""

from __future__ import annotations

import os
import stat

from .._errors import InputError
from .._sizes import human_bytes, memory_limit

#: Memory per byte of CSV while it is parsed (its text, its lines, its table of floats).
MEMORY_PER_BYTE = 12.0
BLOCK = 1 << 20
NUL = bytes(1)


def byte_limit() -> int:
    """The largest telemetry file (bytes) whose parsing fits in the memory free now."""
    return int(memory_limit() / MEMORY_PER_BYTE)


def _too_large(file: str, size: float, limit: int, exact: bool) -> InputError:
    what = f"is {human_bytes(size)}" if exact else f"holds more than {human_bytes(limit)}"
    return InputError(f"the file {what}; reading it would need about "
                      f"{human_bytes(size * MEMORY_PER_BYTE)} of memory, more than this "
                      f"machine has free (files up to {human_bytes(limit)}); nothing was "
                      "read. Split the run into shorter files or resample it to a longer "
                      "period.", file=file, field="--data")


def read_bounded(path, file: str, limit: int | None = None) -> bytes:
    """The bytes of `path`, refused (`InputError` naming `file`) above `limit` bytes
    (default `byte_limit()`) or where its first block holds NUL bytes."""
    limit = byte_limit() if limit is None else int(limit)
    with open(path, "rb") as f:
        st = os.fstat(f.fileno())
        if stat.S_ISREG(st.st_mode) and st.st_size > limit:
            raise _too_large(file, st.st_size, limit, True)
        blocks, total = [], 0
        while True:
            block = f.read(BLOCK)
            if not block:
                break
            if not blocks and NUL in block:
                raise InputError(f"holds NUL bytes (at byte {block.index(NUL)}), so it is "
                                 "not a text CSV file; give the telemetry file itself.",
                                 file=file, field="--data")
            total += len(block)
            if total > limit:
                raise _too_large(file, total, limit, False)
            blocks.append(block)
    return b"".join(blocks)
