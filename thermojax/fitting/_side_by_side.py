"""Independent fits run side by side, with answers that do not depend on how.

A fit spends its time in compiled XLA code, which releases the GIL, so fits on threads
use every core of the machine. What fits share in a process is how finely each model
structure is integrated (`_integration.shared_substeps`); fits run here each start from
that memory as it was before any of them ran and it keeps the most each needed after
all finish, so their answers are the same on one thread or many, in any order.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from .._blas_threads import one_blas_thread
from ._integration import merge_substeps, substep_memory, substep_snapshot

T = TypeVar("T")


def side_by_side(tasks: list[Callable[[], T]]) -> list[T]:
    """`[task() for task in tasks]`, on up to `os.cpu_count()` threads. An exception
    raised by a task is raised after every task has finished (the first in task
    order)."""
    memories = [substep_snapshot() for _ in tasks]

    def run(task, memory):
        with substep_memory(memory):
            try:
                return task(), None
            except Exception as err:
                return None, err

    workers = min(len(tasks), os.cpu_count() or 1)
    if workers <= 1:
        done = [run(task, memory) for task, memory in zip(tasks, memories)]
    else:
        with one_blas_thread(), ThreadPoolExecutor(
                workers, thread_name_prefix="thermojax-fit") as pool:
            done = list(pool.map(run, tasks, memories))
    for memory in memories:
        merge_substeps(memory)
    for _, err in done:
        if err is not None:
            raise err
    return [result for result, _ in done]
