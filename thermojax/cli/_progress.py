"""Progress on the command line: every message the library reports, and on a terminal a
live status line with the time spent since the last one (so a long compilation or a
Kalman fit never looks hung). Plain lines when the output is not a terminal; nothing
under `--quiet`. While a command runs, Ctrl-C is remembered as well as raised, so that an
interrupt Python swallows (one that lands in a garbage-collection callback or a `__del__`
is printed as "Exception ignored" and dropped) is raised again at the next message."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time


class Progress:
    """A `progress(msg)` callable for the library's long functions.

    **Arguments:** `quiet` (print nothing), `task` (the status line's words, such as
    "fitting"), `stream` (default stdout).
    """

    def __init__(self, task: str, *, quiet: bool = False, stream=None):
        self.task = task
        self.quiet = quiet
        self.stream = stream if stream is not None else sys.stdout
        self.live = not quiet and self.stream.isatty()
        self._status = None
        self._last = "starting"
        self._since = time.perf_counter()
        self.interrupted = False  # Ctrl-C was pressed while `running`

    def __call__(self, msg: str) -> None:
        if self.interrupted:
            raise KeyboardInterrupt
        if self.quiet:
            return
        self._last, self._since = msg, time.perf_counter()
        if self._status is not None:
            self._console.print(f"  {msg}", highlight=False, markup=False)
            self.refresh()
        else:
            print(f"  {msg}", file=self.stream, flush=True)

    def refresh(self) -> None:
        """Redraw the status line: task, last message, seconds since it."""
        from rich.markup import escape

        if self._status is not None:
            seconds = time.perf_counter() - self._since
            self._status.update(f"{escape(self.task)}: {escape(self._last)} ({seconds:.0f} s)")

    @contextlib.contextmanager
    def running(self):
        """While open, a terminal shows a spinner with the task, the last message and the
        seconds since it (rich's status line, refreshed by its own thread), and Ctrl-C
        sets `interrupted` (`_catching_interrupts`)."""
        with self._catching_interrupts():
            if not self.live:
                yield self
                return
            with self._status_line():
                yield self

    @contextlib.contextmanager
    def _catching_interrupts(self):
        """SIGINT raises `KeyboardInterrupt`, as Python's own handler does, and sets
        `interrupted`; where Python swallows it (`sys.unraisablehook`) nothing is printed.
        The previous handler and hook come back on exit. Only in the main thread (where
        Python delivers signals)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def on_sigint(signum, frame):
            self.interrupted = True
            raise KeyboardInterrupt

        def on_unraisable(unraisable):  # the interrupt comes again at the next message
            if not isinstance(unraisable.exc_value, KeyboardInterrupt):
                previous_hook(unraisable)

        previous = signal.signal(signal.SIGINT, on_sigint)
        previous_hook, sys.unraisablehook = sys.unraisablehook, on_unraisable
        try:
            yield
        finally:
            signal.signal(signal.SIGINT, previous)
            sys.unraisablehook = previous_hook

    @contextlib.contextmanager
    def _status_line(self):
        from rich.console import Console

        self._console = Console(file=self.stream)
        with self._console.status(self.task, spinner="dots") as status:
            self._status = status
            self.refresh()
            ticker = _Ticker(self)
            try:
                with ticker:
                    yield self
            finally:
                self._status = None


class _Ticker:
    """Redraws the status line once a second, so the seconds count up between messages."""

    def __init__(self, progress: Progress):
        self.progress = progress
        self._stop = None

    def __enter__(self):
        import threading

        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(timeout=2)

    def _run(self):
        while not self._stop.wait(1.0):
            self.progress.refresh()
