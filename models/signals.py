"""SIGTERM handled as Ctrl-C by the training commands.

A cluster pre-empts a job with SIGTERM and, a grace period later, SIGKILL; a service manager stops one the
same way. Python's default for SIGTERM ends the process on the spot: no word of what the run kept, and the
job processes of ``models.reproduce`` left running without their parent. Raised as a KeyboardInterrupt
instead, it takes the path Ctrl-C takes: the files being written are abandoned whole (their ``.tmp`` removed),
the job processes are stopped, and the command says in one line what it kept and how to go on.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


class Stopped(KeyboardInterrupt):
    """SIGTERM, raised as Ctrl-C is; ``args[0]`` is the signal's number."""


def _stop(signum: int, frame: object) -> None:
    raise Stopped(signum)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Stopped` (a KeyboardInterrupt). Outside the main thread, where
    Python cannot set a handler, the block runs with the signal as it was."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stop_status(exc: KeyboardInterrupt, interrupted_status: int) -> int:
    """The exit status of a command stopped by ``exc``: 128 + SIGTERM's number (143), as if the signal had ended
    it, for :class:`Stopped`; ``interrupted_status`` (Ctrl-C's 130) otherwise."""
    return 128 + exc.args[0] if isinstance(exc, Stopped) else interrupted_status
