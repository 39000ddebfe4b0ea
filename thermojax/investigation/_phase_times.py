"""Where a step of the loop spends its wall time: named phases (its fit confirmed, the
score tests, the refits, the held-out folds, waiting for the missing heat, the heat
network) and, counted inside them, JAX's compilation (tracing, lowering and XLA's
compile, from JAX's own event durations: `jax.monitoring`).

`step_phases()` opens a step's tally; `phase(name)` adds the time spent in its block.
Work on the loop's background threads is not counted in a phase (it overlaps the
phases), and neither is its compilation.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import jax

COMPILATION = "compilation"
_COMPILE_EVENTS = frozenset({"/jax/core/compile/backend_compile_duration",
                             "/jax/core/compile/jaxpr_to_mlir_module_duration",
                             "/jax/core/compile/jaxpr_trace_duration"})
_tally: ContextVar[dict | None] = ContextVar("thermojax_step_phases", default=None)


def _on_duration(event: str, duration: float, **_kw) -> None:
    tally = _tally.get()
    if tally is not None and event in _COMPILE_EVENTS:
        tally[COMPILATION] += duration


jax.monitoring.register_event_duration_secs_listener(_on_duration)


@contextmanager
def step_phases() -> Iterator[dict[str, float]]:
    """A fresh tally, phase name -> seconds, for the step run inside the block."""
    token = _tally.set(defaultdict(float))
    try:
        yield _tally.get()
    finally:
        _tally.reset(token)


@contextmanager
def phase(name: str) -> Iterator[None]:
    """Add the wall time of the block to phase `name` of the open tally (none: nothing)."""
    tally, t0 = _tally.get(), time.perf_counter()
    try:
        yield
    finally:
        if tally is not None:
            tally[name] += time.perf_counter() - t0


def phases_in_words(tally: dict[str, float], total: float) -> str:
    """`"412 s: refits 301 s, held-out folds 60 s, …; compilation 120 s of it"`, the
    phases largest first, those under 1 % of `total` left out."""
    parts = [f"{k} {v:.0f} s" for k, v in sorted(tally.items(), key=lambda kv: -kv[1])
             if k != COMPILATION and v >= 0.01 * total]
    text = f"{total:.0f} s" + (": " + ", ".join(parts) if parts else "")
    if tally.get(COMPILATION, 0.0) >= 0.01 * total:
        text += f"; compilation {tally[COMPILATION]:.0f} s of it"
    return text
