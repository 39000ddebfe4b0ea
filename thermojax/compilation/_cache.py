"""A persistent cache of compiled XLA programs, so a second run of the same model skips
compilation (the bulk of a first fit's time on a CPU).

The command line turns it on by default (`--no-cache` to turn it off); API users call
`enable_compilation_cache()`. Entries live under the user's cache folder, in one
subfolder per JAX and jaxlib version, and JAX keys every entry by the program, the
compiler options and the backend as well, so a cache is never read across versions.
"""

from __future__ import annotations

import os
from pathlib import Path

MAX_BYTES = 2 * 1024**3  # the cache evicts least recently used entries beyond this


def default_cache_dir() -> Path:
    """`$THERMOJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/thermojax`, else `~/.cache/thermojax`;
    then one subfolder per JAX and jaxlib version."""
    import jax
    import jaxlib

    root = os.environ.get("THERMOJAX_CACHE_DIR")
    if root is None:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        root = Path(base) / "thermojax"
    return Path(root) / f"jax-{jax.__version__}-jaxlib-{jaxlib.__version__}"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Store compiled programs in `path` (default `default_cache_dir()`) and reuse them.

    Returns the folder, or `None` when it cannot be created (the cache is then left off:
    a read-only home must not stop a fit).
    """
    import jax

    folder = Path(path) if path is not None else default_cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    _discard_damaged_entries()
    return folder


def _discard_damaged_entries() -> None:
    """Make JAX remove a persistent-cache entry it cannot read back (a damaged file), so
    the program is compiled and stored afresh instead of warned about on every later run
    (JAX only warns and recompiles). Wraps JAX's reader where this JAX has it; else
    nothing changes."""
    try:
        from jax._src import compilation_cache as cc
    except ImportError:  # pragma: no cover
        return
    read = getattr(cc, "get_executable_and_time", None)
    if read is None or getattr(read, "_thermojax_discards", False):
        return

    def get_executable_and_time(cache_key, compile_options, backend, *args, **kwargs):
        try:
            return read(cache_key, compile_options, backend, *args, **kwargs)
        except Exception as err:
            import warnings

            cache = getattr(cc, "_cache", None)
            folder = getattr(cache, "path", None)
            if folder is not None:
                for suffix in ("-cache", "-atime"):
                    try:
                        (Path(folder) / f"{cache_key}{suffix}").unlink(missing_ok=True)
                    except OSError:
                        pass
                warnings.warn(f"the compile-cache entry {cache_key} was damaged "
                              f"({type(err).__name__}); it was removed and the program is "
                              "compiled afresh", RuntimeWarning, stacklevel=2)
                return None, None
            raise

    get_executable_and_time._thermojax_discards = True
    cc.get_executable_and_time = get_executable_and_time
