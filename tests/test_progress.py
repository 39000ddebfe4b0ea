"""The command line's progress reporter: Ctrl-C that Python swallows is not lost."""

import os
import signal
import time

import pytest

from thermojax.cli._progress import Progress


def swallowing_interrupt():
    """A SIGINT that lands where Python ignores exceptions (as in a garbage-collection
    callback, where it is printed as "Exception ignored" and dropped)."""
    try:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1.0)  # the handler runs here
    except KeyboardInterrupt:
        pass


def test_swallowed_interrupt_is_raised_at_the_next_message():
    before = signal.getsignal(signal.SIGINT)  # Python's own, or SIG_IGN under `nohup &`
    progress = Progress("testing", quiet=True)
    with pytest.raises(KeyboardInterrupt):
        with progress.running():
            progress("before")
            swallowing_interrupt()
            assert progress.interrupted
            progress("after")  # raises
    # the previous handler is back (a process started in the background ignores SIGINT
    # from the start, and Python then installs no handler of its own)
    assert signal.getsignal(signal.SIGINT) is before


def test_swallowed_interrupt_after_the_last_message_exits_130(monkeypatch, capsys):
    """A command whose last Ctrl-C was swallowed still ends as interrupted (exit 130)."""
    import argparse
    import types

    from thermojax.cli import _main

    def finishing(args):
        swallowing_interrupt()
        return 0

    args = argparse.Namespace(command="test", func=finishing, quiet=True)
    monkeypatch.setattr(_main, "build_parser",
                        lambda: types.SimpleNamespace(parse_args=lambda argv: args))
    assert _main.main(["test"]) == 130
    assert "interrupted" in capsys.readouterr().err


def test_swallowed_interrupt_prints_no_traceback():
    """Python reports an exception it cannot raise (`sys.unraisablehook`) with a
    traceback; a swallowed Ctrl-C is not reported, anything else still is."""
    import sys
    import types

    seen = []
    previous = sys.unraisablehook
    sys.unraisablehook = seen.append
    try:
        progress = Progress("testing", quiet=True)
        with progress.running():
            for exc in (KeyboardInterrupt(), ValueError("other")):
                sys.unraisablehook(types.SimpleNamespace(exc_type=type(exc), exc_value=exc,
                                                         exc_traceback=None, err_msg=None,
                                                         object=None))
        assert [type(u.exc_value) for u in seen] == [ValueError]
        assert sys.unraisablehook == seen.append  # restored
    finally:
        sys.unraisablehook = previous
