"""Chunks across devices and processes.

Within a process, a chunk's units are split over every local device: a one-axis
`jax.sharding.Mesh` named `"units"` over `jax.local_devices()`, the per-unit arrays
placed with `NamedSharding(mesh, P("units"))` and the study's vmapped program jitted
over them, so XLA runs each device's slice of units where it lives. One CPU device, N
forced host devices (`XLA_FLAGS=--xla_force_host_platform_device_count=N`) or a GPU
need no change: a chunk is padded to a multiple of the device count (with the next
units' indices, whose results are dropped).

Across processes (hosts), each process takes its own share of the chunks: chunk `c`
belongs to process `c mod process_count`. After `jax.distributed.initialize()`, the
share comes from `jax.process_index()` and `jax.process_count()`; without it (or to
test on one machine) from the environment variables `THERMOJAX_PROCESS_INDEX` and
`THERMOJAX_PROCESS_COUNT`. Every process writes its finished chunks into the same
folder (a shared filesystem); whichever process finds all chunks finished writes the
report, and `--resume` on any one machine afterwards merges them.
"""

from __future__ import annotations

import os

import numpy as np

from .._errors import InputError


def process_share() -> tuple[int, int]:
    """`(process_index, process_count)` of this process (see the module docstring)."""
    env_i, env_n = os.environ.get("THERMOJAX_PROCESS_INDEX"), os.environ.get(
        "THERMOJAX_PROCESS_COUNT")
    if env_i is not None or env_n is not None:
        try:
            i, n = int(env_i or 0), int(env_n or 1)
        except ValueError:
            raise InputError("THERMOJAX_PROCESS_INDEX and THERMOJAX_PROCESS_COUNT must be "
                             f"whole numbers, got {env_i!r} and {env_n!r}.",
                             field="THERMOJAX_PROCESS_INDEX") from None
        if not (n >= 1 and 0 <= i < n):
            raise InputError(f"process index {i} of {n}: expected 0 <= index < count.",
                             field="THERMOJAX_PROCESS_INDEX")
        return i, n
    if os.environ.get("THERMOJAX_DISTRIBUTED"):
        import jax

        return jax.process_index(), jax.process_count()
    return 0, 1


def initialize_distributed() -> None:
    """`jax.distributed.initialize(...)` when `THERMOJAX_DISTRIBUTED=1`: the coordinator
    from `JAX_COORDINATOR_ADDRESS` (`host:port`), the process count and this process's
    index from `JAX_NUM_PROCESSES` and `JAX_PROCESS_ID` (JAX itself reads only the
    first); whatever is unset, JAX detects from a cluster's environment (SLURM, Open
    MPI, ...)."""
    if not os.environ.get("THERMOJAX_DISTRIBUTED"):
        return
    import jax

    given = {}
    for var, key in (("JAX_NUM_PROCESSES", "num_processes"), ("JAX_PROCESS_ID", "process_id")):
        text = os.environ.get(var)
        if text is None:
            continue
        try:
            given[key] = int(text)
        except ValueError:
            raise InputError(f"{var} must be a whole number, got {text!r}.", field=var) from None
    n, i = given.get("num_processes"), given.get("process_id")
    if n is not None and n < 1 or n is not None and i is not None and not 0 <= i < n:
        raise InputError(f"JAX_PROCESS_ID {i} of JAX_NUM_PROCESSES {n}: expected "
                         "0 <= id < count.", field="JAX_PROCESS_ID")
    try:
        jax.distributed.initialize(**given)
    except (ValueError, RuntimeError) as err:
        raise InputError(f"THERMOJAX_DISTRIBUTED is set but jax.distributed could not start: "
                         f"{err} Set JAX_COORDINATOR_ADDRESS (host:port of process 0), "
                         "JAX_NUM_PROCESSES and JAX_PROCESS_ID on every host, or run "
                         "under a cluster JAX detects (SLURM, Open MPI).",
                         field="THERMOJAX_DISTRIBUTED") from None


def chunks_of_process(n_chunks: int, index: int, count: int) -> list[int]:
    """Chunk numbers of process `index` of `count`: `c` with `c mod count == index`.
    Disjoint across processes, together every chunk."""
    return [c for c in range(n_chunks) if c % count == index]


def units_mesh():
    """A one-axis mesh `"units"` over this process's devices."""
    import jax
    from jax.sharding import Mesh

    return Mesh(np.array(jax.local_devices()), ("units",))


def padded_size(n: int, mesh) -> int:
    """`n` rounded up to a multiple of the mesh's device count."""
    d = mesh.devices.size
    return -(-n // d) * d


def shard_units(arrays, mesh):
    """Put every array of the pytree `arrays` on `mesh`, its first axis (units) split
    over the devices."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec as P

    sharding = NamedSharding(mesh, P("units"))
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding), arrays)


def replicate(arrays, mesh):
    """Put every array of `arrays` whole on every device of `mesh`."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec as P

    sharding = NamedSharding(mesh, P())
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding), arrays)
