"""Keep a long session clear of the kernel's limit on memory mappings.

Every XLA CPU executable holds several memory mappings. An investigation compiles a
program per candidate structure (about 4,000 mappings per investigation of a small
model), and a Linux process that nears `vm.max_map_count` (65,530 by default) crashes
inside the compiler. Dropping JAX's compiled programs when the count grows large costs
only the recompilation of the few still in use.
"""

from __future__ import annotations

import gc

MAPPINGS_LIMIT = 20_000


def memory_mappings() -> int | None:
    """The number of memory mappings of this process (None where /proc is absent)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


def release_compiled_if_crowded(limit: int = MAPPINGS_LIMIT) -> bool:
    """`jax.clear_caches()` if the process holds more than `limit` mappings; whether it did."""
    n = memory_mappings()
    if n is None or n <= limit:
        return False
    import jax

    from .compilation._traced_cache import forget_programs

    forget_programs()
    jax.clear_caches()
    gc.collect()
    return True
