"""Diagnostic figures drawn on a background thread while the investigation goes on.

A step's five PNGs take 0.5-3 s of matplotlib; the loop's next fits spend most of
their time in compiled JAX code, which releases the GIL. `PlotsAhead` draws a step's
figures as soon as its fit is final, on one worker thread, and hands them to the report
when it is written, if the report asks for the very same figures (same traces object,
columns, inputs, titles, units); otherwise the report's figures are drawn again, after
the ones ahead (one worker, first in first out: a stale figure never overwrites a
current one). All drawing of these figures happens on the worker thread; the loop's
other figures are drawn on its own thread meanwhile, and matplotlib's text layout, which
is not thread-safe, runs under `_plots.save_figure`'s lock.
"""

from __future__ import annotations

import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ._diagnostic_plots import diagnostic_plots


class PlotsAhead:
    """`diagnostic_plots` calls run on one background thread, keyed by their arguments.

    `ahead(...)` queues the figures (once per arguments and traces); `draw(...)` (same
    arguments) returns their file names, waiting for the queued job when one matches,
    else queueing a new one. A job queued `staged` (a step the loop may not take) draws
    into a hidden folder of `out_dir`, and its files move into `out_dir` only when drawn.
    `close()` cancels what has not started and removes what was staged and not drawn
    (call it when the loop ends, however it ends)."""

    STAGING = ".figures-ahead"

    def __init__(self):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="thermojax-plots")
        self._jobs: list[list] = []  # [key, runs, Future, staging folder or None]
        self._staging_roots: set[Path] = set()

    @staticmethod
    def _key(out_dir, prefix, columns, input_names, boundary_inputs, kwargs) -> tuple:
        units = kwargs.get("units") or {}
        return (str(Path(out_dir)), prefix, tuple(columns), tuple(input_names),
                tuple(boundary_inputs), kwargs.get("time_scale"), kwargs.get("title"),
                kwargs.get("max_lag"), tuple(sorted(units.items())))

    def _find(self, key, runs):
        return next((job for job in reversed(self._jobs)
                     if job[0] == key and job[1] is runs), None)

    def ahead(self, out_dir, prefix: str, columns, runs: list, input_names,
              boundary_inputs=(), staged: bool = False, **kwargs) -> None:
        """Queue `diagnostic_plots(out_dir, prefix, columns, runs, ...)`. The run traces
        are copied (shallow): the caller may replace a trace's arrays afterwards."""
        key = self._key(out_dir, prefix, columns, input_names, boundary_inputs, kwargs)
        if self._find(key, runs) is not None:
            return
        folder = None
        if staged:
            root = Path(out_dir) / self.STAGING
            self._staging_roots.add(root)
            folder = root / str(len(self._jobs))
        copies = [dict(r) for r in runs]
        job = self._pool.submit(diagnostic_plots, folder or out_dir, prefix, columns, copies,
                                input_names, boundary_inputs, **kwargs)
        self._jobs.append([key, runs, job, folder])

    def draw(self, out_dir, prefix: str, columns, runs: list, input_names,
             boundary_inputs=(), **kwargs) -> dict[str, str]:
        """`diagnostic_plots`'s file names for these arguments: a matching queued job's
        (the same `runs` object), else a new job's, once it is done."""
        key = self._key(out_dir, prefix, columns, input_names, boundary_inputs, kwargs)
        job = self._find(key, runs)
        if job is None:
            self.ahead(out_dir, prefix, columns, runs, input_names, boundary_inputs, **kwargs)
            job = self._jobs[-1]
        names = job[2].result()
        if job[3] is not None:  # staged: into place
            for name in names.values():
                os.replace(job[3] / name, Path(out_dir) / name)
            job[3] = None
        return names

    def close(self) -> None:
        """Cancel the queued jobs that have not started; wait for the running one; remove
        the staged figures never drawn."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        for root in self._staging_roots:
            shutil.rmtree(root, ignore_errors=True)
