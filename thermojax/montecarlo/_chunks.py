"""A folder of chunks: each chunk of units written whole (temporary file in the same
folder, fsync, `os.replace`), a manifest with the config's hash, and resume.

Layout of a study folder:

    manifest.json            schema, config hash, the resolved config, n_units, chunk_size
    chunks/chunk_00000.npz   one chunk's arrays (NPZ, uncompressed)
    chunks/chunk_00000.json  its record: units, sha256 and size of the .npz

A chunk is finished when its record exists, names the right units, and the .npz has the
recorded sha256 and loads; anything else (missing, half written, corrupt) is computed
again. The record is written after the data, so a crash between the two leaves an
unfinished chunk. Each chunk has its own files, so several processes can fill one
folder (each its own share of chunks) without sharing a file but the manifest, which is
written once with the same content by whoever comes first.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .._errors import InputError

SCHEMA = 1


def config_hash(resolved: dict) -> str:
    """sha256 of the canonical JSON of a resolved config (sorted keys)."""
    text = json.dumps(resolved, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` whole or not at all: a temporary file in the same folder,
    flushed and fsynced, then `os.replace`d over `path`, and the folder fsynced."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.partial-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:  # some filesystems cannot fsync a folder
        pass


def chunk_units(n_units: int, chunk_size: int, chunk: int) -> np.ndarray:
    """Unit indices of `chunk` (the last chunk may be short)."""
    return np.arange(chunk * chunk_size, min((chunk + 1) * chunk_size, n_units), dtype=np.int64)


class ChunkStore:
    """The chunk folder of one study (see the module docstring)."""

    def __init__(self, folder: Path, resolved: dict, n_units: int, chunk_size: int):
        self.folder = Path(folder)
        self.resolved = resolved
        self.hash = config_hash(resolved)
        self.n_units = int(n_units)
        self.chunk_size = int(chunk_size)
        self.n_chunks = -(-self.n_units // self.chunk_size)
        self.chunks_dir = self.folder / "chunks"

    @property
    def manifest_path(self) -> Path:
        return self.folder / "manifest.json"

    def manifest(self) -> dict:
        return {"schema": SCHEMA, "config_hash": self.hash, "n_units": self.n_units,
                "chunk_size": self.chunk_size, "n_chunks": self.n_chunks,
                "format": "npz", "config": self.resolved}

    def open(self, resume: bool) -> None:
        """Create the folder (fresh) or check it for a resume.

        On resume, a manifest of a different config is refused with the reason; a fresh
        start removes this store's old chunk files (never anything else)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        if resume and self.manifest_path.is_file():
            try:
                old = json.loads(self.manifest_path.read_text())
            except (OSError, ValueError) as err:
                raise InputError(f"the manifest cannot be read ({err}); start afresh with "
                                 "--force.", file=str(self.manifest_path)) from None
            if old.get("config_hash") != self.hash:
                diff = _differences(old.get("config", {}), self.resolved)
                raise InputError(
                    "this folder was written by a different config, so its chunks cannot be "
                    f"resumed with this one (differs in: {', '.join(diff) or 'the hash'}); "
                    "choose another --out, or pass --force to start afresh.",
                    file=str(self.manifest_path), field="config_hash")
        elif not resume and self.chunks_dir.is_dir():
            for p in self.chunks_dir.glob("chunk_*"):
                p.unlink()
        self.chunks_dir.mkdir(exist_ok=True)
        for p in self.chunks_dir.glob(".chunk_*.partial-*"):  # a crash's leftovers
            p.unlink(missing_ok=True)
        if not self.manifest_path.is_file() or not resume:
            atomic_write_bytes(self.manifest_path,
                               json.dumps(self.manifest(), indent=1, sort_keys=True,
                                          default=str).encode())

    def paths(self, chunk: int) -> tuple[Path, Path]:
        stem = self.chunks_dir / f"chunk_{chunk:05d}"
        return stem.with_suffix(".npz"), stem.with_suffix(".json")

    def load(self, chunk: int) -> dict[str, np.ndarray] | None:
        """The chunk's arrays if it is finished and intact, else None."""
        data, record = self.paths(chunk)
        try:
            rec = json.loads(record.read_text())
            raw = data.read_bytes()
        except (OSError, ValueError):
            return None
        units = chunk_units(self.n_units, self.chunk_size, chunk)
        if (rec.get("sha256") != hashlib.sha256(raw).hexdigest()
                or rec.get("units") != [int(units[0]), int(units[-1]) + 1]
                or rec.get("config_hash") != self.hash):
            return None
        try:
            with np.load(io.BytesIO(raw), allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception:  # noqa: BLE001 - any failure to load is a corrupt chunk
            return None
        if not np.array_equal(arrays.get("unit"), units):
            return None
        return arrays

    def is_finished(self, chunk: int) -> bool:
        return self.load(chunk) is not None

    def write(self, chunk: int, arrays: dict[str, np.ndarray]) -> None:
        """Write a chunk whole: the .npz, then its record."""
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        raw = buf.getvalue()
        data, record = self.paths(chunk)
        units = chunk_units(self.n_units, self.chunk_size, chunk)
        record.unlink(missing_ok=True)
        atomic_write_bytes(data, raw)
        atomic_write_bytes(record, json.dumps({
            "chunk": chunk, "units": [int(units[0]), int(units[-1]) + 1],
            "sha256": hashlib.sha256(raw).hexdigest(), "bytes": len(raw),
            "config_hash": self.hash}).encode())

    def gather(self) -> dict[str, np.ndarray] | None:
        """Every chunk's arrays concatenated in unit order, or None if any is unfinished."""
        parts = []
        for c in range(self.n_chunks):
            got = self.load(c)
            if got is None:
                return None
            parts.append(got)
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{k}.")
        elif json.dumps(a, sort_keys=True, default=str) != json.dumps(b, sort_keys=True,
                                                                      default=str):
            out.append(f"{prefix}{k}")
    return out
