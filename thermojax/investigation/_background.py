"""Work the loop starts on threads of its own, beside the step (`_on_thread`): the
missing heat while the candidates are scored and refitted (`_beside`), and a
candidate's score-test inputs while its held-out folds are fitted (`score_ahead`)."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor

from ._diagnose_step import scoring_inputs
from ._step import Step
from ..measurements._telemetry import Telemetry


def _on_thread(fn, *args) -> Future:
    """`fn(*args)` started on a thread of its own; its `Future`."""
    pool = ThreadPoolExecutor(1, thread_name_prefix="thermojax-beside")
    future = pool.submit(fn, *args)
    pool.shutdown(wait=False)
    return future


def _beside(task, *args, say):
    """Start `task(*args, say)` on a thread of its own; returns `wait()`, which waits
    for it, says what it said (held till then, so that its lines do not interleave with
    the step's) and returns its result. The missing heat, which only the step's end reads,
    so runs beside the candidates' scoring and refits: its single-threaded programs fill
    the core the refits leave idle at their waves' ends (5 s a step on PRBS1)."""
    said: list[str] = []
    future = _on_thread(task, *args, said.append)

    def wait():
        try:
            return future.result()
        finally:
            for line in said:
                say(line)
    return wait


def score_ahead(step: Step, runs: list[Telemetry], likelihood: str) -> None:
    """Compute `step`'s `scoring_inputs` on a thread of its own (`step.scoring`), for
    `diagnose_step` to take when it scores the step: a candidate's, while its held-out
    folds are fitted, so that their programs' compilation (1-3 s a step on PRBS1) is
    off the loop's single-threaded scoring. A failure is raised where they are taken."""
    step.scoring = (likelihood, _on_thread(scoring_inputs, step, runs, likelihood))
