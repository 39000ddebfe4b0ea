"""What an observer artifact must satisfy before anything runs it (NumPy and the standard
library only): a content hash recorded at export and verified at every load, the
metadata's kinds (lists of named entries, a plausible rate that matches its period, a
known fixed-point format with a usable scale), a stable discretization (|eig(Phi)| < 1)
and stable error dynamics for every sensor subset, and offsets that are an equilibrium.
A tampered or damaged artifact is refused naming the file and the field, never run."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from .._errors import InputError

HASH_FIELD = "content_sha256"
#: Hz: an observer step rate outside this range is not a thermal observer's.
RATE_RANGE_HZ = (1e-4, 1e5)
#: A spectral radius at or above this is not stable (a margin for rounding).
STABLE_BELOW = 1.0 - 1e-12
#: K: the offsets' equilibrium residual allowed, relative to their size.
EQUILIBRIUM_TOLERANCE = 1e-6


def content_hash(meta: dict, arrays: dict) -> str:
    """SHA-256 of the metadata (canonical JSON, without `HASH_FIELD`) and of every array
    (name, dtype, shape and bytes, by name)."""
    h = hashlib.sha256()
    body = {k: v for k, v in meta.items() if k != HASH_FIELD}
    h.update(json.dumps(body, sort_keys=True, ensure_ascii=True, allow_nan=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"\0{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _error(cls, message, file, field):
    return cls(message, file=str(file), field=field)


def check_metadata(meta: dict, meta_path, cls=InputError) -> None:
    """Kinds and values of the fields every use reads, before any array is used."""
    for key in ("states", "inputs", "outputs"):
        entries = meta[key]
        if not isinstance(entries, list) or not all(
                isinstance(e, dict) and isinstance(e.get("name"), str) and e["name"]
                for e in entries):
            raise _error(cls, f"'{key}' must be a list of entries each with a 'name' (as "
                         f"export writes it), got {str(entries)[:80]!r}.", meta_path, key)
    rate, dt = meta["rate_hz"], meta["dt_s"]
    for key, v in (("rate_hz", rate), ("dt_s", dt)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v <= 0:
            raise _error(cls, f"'{key}' must be a positive number, got {v!r}.", meta_path, key)
    if not RATE_RANGE_HZ[0] <= rate <= RATE_RANGE_HZ[1]:
        raise _error(cls, f"a rate of {rate:g} Hz is not a thermal observer's (expected "
                     f"{RATE_RANGE_HZ[0]:g} to {RATE_RANGE_HZ[1]:g} Hz).", meta_path, "rate_hz")
    if abs(rate * dt - 1.0) > 1e-9:
        raise _error(cls, f"rate_hz {rate:g} does not match dt_s {dt:g} (their product must "
                     "be 1): the matrices were discretized for one period only; export the "
                     "observer again at the rate wanted.", meta_path, "rate_hz")
    fx = meta["fixed"]
    if fx is None:
        return
    from ._formats import FORMATS

    if not isinstance(fx, dict) or fx.get("format") not in FORMATS:
        got = fx.get("format") if isinstance(fx, dict) else fx
        raise _error(cls, f"unknown fixed-point format {got!r}; known are "
                     f"{', '.join(sorted(FORMATS))}.", meta_path, "fixed.format")
    fmt = FORMATS[fx["format"]]
    for key, want in (("word_bits", fmt.word_bits), ("frac_bits", fmt.frac_bits)):
        if fx.get(key) != want:
            raise _error(cls, f"format {fmt.name} has {key} {want}, but the artifact records "
                         f"{fx.get(key)!r}.", meta_path, f"fixed.{key}")
    scale = fx.get("state_scale_K")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (
            math.isfinite(scale) and scale > 0):
        raise _error(cls, f"the state scale must be a positive number of kelvin, got "
                     f"{scale!r}.", meta_path, "fixed.state_scale_K")


def check_dynamics(arrays: dict, system, npz_path, cls=InputError,
                   integrating: bool = False) -> None:
    """A stable discretization and stable error dynamics for every sensor subset, and
    offsets that are an equilibrium of the matrices. `integrating`: the artifact
    reconstructs an input as a random-walk state (`reconstruct`), whose eigenvalue is 1
    exactly; then |eig(Phi)| ≤ 1."""
    rho = float(np.max(np.abs(np.linalg.eigvals(arrays["Phi"])), initial=0.0))
    if not (rho <= 1.0 + 1e-12 if integrating else rho < STABLE_BELOW):
        raise _error(cls, f"the discretized model is not stable (largest |eig(Phi)| = "
                     f"{rho:.6g}, must be below 1): the array was modified or the model "
                     "has no path to ambient.", npz_path, "Phi")
    p = arrays["C"].shape[0]
    for mask in range(1, 1 << p):
        subset = [j for j in range(p) if mask >> j & 1]
        ev = np.linalg.eigvals(system.error_dynamics(subset))
        r = float(np.max(np.abs(ev), initial=0.0)) if np.all(np.isfinite(ev)) else math.inf
        if not (r <= 1.0 + 1e-12 if integrating else r < STABLE_BELOW):
            raise _error(cls, f"the gains of sensor subset {subset} (gain_table[{mask}]) give "
                         f"unstable error dynamics (spectral radius {r:.6g}, must be below 1): "
                         "the gains were modified.", npz_path, "gain_table")
    a = arrays
    x_ref, u_ref, y_ref = a["x_ref"], a["u_ref"], a["y_ref"]
    size = 1.0 + max(np.abs(x_ref).max(initial=0.0), np.abs(u_ref).max(initial=0.0))
    dx = np.abs(a["Phi"] @ x_ref + (a["B0"] + a["B1"]) @ u_ref - x_ref).max(initial=0.0)
    dy = np.abs(a["C"] @ x_ref + a["D"] @ u_ref - y_ref).max(initial=0.0)
    tol = EQUILIBRIUM_TOLERANCE * size
    if not max(dx, dy) <= tol:
        field = "x_ref" if not dx <= tol else "y_ref"
        raise _error(cls, f"the reference offsets are not an equilibrium of the matrices "
                     f"(off by {max(dx, dy):.3g}): the offsets or matrices were modified.",
                     npz_path, field)


def check_hash(meta: dict, arrays: dict, meta_path, cls=InputError) -> None:
    """The content hash recorded at export, where there is one (artifacts written before
    it have none and are checked by the rest alone)."""
    want = meta.get(HASH_FIELD)
    if want is None:
        return
    if content_hash(meta, arrays) != want:
        raise _error(cls, "the artifact's content does not match the hash recorded when it "
                     "was exported: observer.json or observer.npz was modified or damaged "
                     "since. Export the observer again.", meta_path, HASH_FIELD)
