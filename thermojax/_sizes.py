"""Sizes checked before work: a job whose predicted memory cannot fit is refused with the
prediction, before anything is allocated (a Monte Carlo study of 1e9 units, a simulation at
`--dt 1e-300`, `--data /dev/zero`)."""

from __future__ import annotations

from ._errors import InputError

#: Above this share of the memory available now, a job is refused before it starts.
MEMORY_SHARE = 0.8
#: Where the available memory is unknown (no /proc/meminfo), this many bytes.
UNKNOWN_AVAILABLE = 8 * 2 ** 30


def available_memory() -> float:
    """Bytes of memory available now (Linux `MemAvailable`), `UNKNOWN_AVAILABLE` where
    unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float(UNKNOWN_AVAILABLE)


def human_bytes(n: float) -> str:
    """`n` bytes as a short text: 512 B, 3.2 MB, 1.5e+03 GB."""
    n = float(n)
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            value = n / size
            return f"{value:.3g} {unit}" if value < 1e4 else f"{value:.2e} {unit}"
    return f"{n:.0f} B"


def memory_limit() -> float:
    """The most bytes a job may be predicted to need: `MEMORY_SHARE` of what is available."""
    return MEMORY_SHARE * available_memory()


def check_memory(predicted: float, what: str, *, fix: str, file: str | None = None,
                 field: str | None = None, limit: float | None = None) -> None:
    """Refuse (`InputError` naming `file` and `field`) a job of `predicted` bytes above
    `limit` (default `memory_limit()`): `what` says what it is, `fix` what to change."""
    limit = memory_limit() if limit is None else limit
    if not predicted <= limit:  # NaN and inf refused too
        raise InputError(f"{what} would need about {human_bytes(predicted)} of memory, more "
                         f"than the {human_bytes(limit)} this machine has free for it; "
                         f"nothing was started. {fix}", file=file, field=field)
