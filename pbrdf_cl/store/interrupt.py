"""Ctrl-C during a run that writes a store (a sweep, an image fit): it always stops the run.

Python turns SIGINT into a ``KeyboardInterrupt`` wherever the main thread happens to be.  When
that is inside a finaliser or a weakref callback, Python prints ``Exception ignored in ...`` and
carries on: the interrupt is lost and the run goes on to its end.  Inside :func:`recording`
(which the CLI enters around every command) each SIGINT is also recorded, and the loops over
chunks and blocks call :func:`check` after each unit of work, which raises an interrupt that was
recorded but lost.  Outside :func:`recording` (a notebook, a library caller) :func:`check` does
nothing and Python's own handler is left alone.
"""
from __future__ import annotations

import contextlib
import signal
import threading

#: Whether a SIGINT arrived inside :func:`recording` (its first element).
_RECORDED = [False]


def _record_and_raise(signum, frame):
    _RECORDED[0] = True
    raise KeyboardInterrupt


@contextlib.contextmanager
def recording():
    """Within this block a SIGINT raises ``KeyboardInterrupt`` as usual and is recorded for
    :func:`check`; Python's handler is restored after it.  Only the main thread can install a
    signal handler: elsewhere the block changes nothing."""
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield  # another thread, or a caller with a handler of its own: theirs stays
        return
    _RECORDED[0] = False
    signal.signal(signal.SIGINT, _record_and_raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        _RECORDED[0] = False


def check():
    """Raise ``KeyboardInterrupt`` if a SIGINT was recorded (see :func:`recording`): called by a
    run between its units of work, so that an interrupt Python swallowed still stops it."""
    if _RECORDED[0]:
        raise KeyboardInterrupt
