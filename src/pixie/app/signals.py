"""SIGTERM for the ``pixie`` command: turned into an exception (temporary files removed, workers stopped), and a
watchdog so that a clean exit caught mid-operation (a worker pool or a lock) still ends, with exit code 143 and one
``pixie: terminated`` line, ``TERM_GRACE_S`` seconds after the signal.
"""

from __future__ import annotations

import os
import sys
import threading

TERM_GRACE_S = 10.0  # after SIGTERM, the clean exit (temporary files removed, workers stopped) gets this long
TERM: list = []  # SIGTERM received (progress ticks raise Terminated when set)
_PRINTED: list = []


class Terminated(BaseException):
    """SIGTERM, turned into an exception so that temporary files are removed and workers stopped."""


def say_terminated() -> None:
    """Print the one ``pixie: terminated`` line (once)."""
    if not _PRINTED:
        _PRINTED.append(True)
        print("pixie: terminated", file=sys.stderr, flush=True)


def _force_exit() -> None:
    say_terminated()
    os._exit(143)


def on_sigterm(signum, frame) -> None:
    """The SIGTERM handler: arm the watchdog, then raise :class:`Terminated` (not inside logging's fork hooks)."""
    if not TERM:
        timer = threading.Timer(TERM_GRACE_S, _force_exit)
        timer.daemon = True
        timer.start()
    TERM.append(signum)  # a progress tick raises it where Python would ignore it (fork hooks, e.g. logging's)
    if frame is None or frame.f_code.co_name not in ("_acquireLock", "_releaseLock", "_at_fork_reinit"):
        raise Terminated()
