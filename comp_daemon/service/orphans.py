"""Worker processes that end with the daemon.

A pool worker (job or upload check) waits for work on a pipe whose writing end it holds itself, so
it never sees the daemon go: after a ``kill -9`` of the daemon it would live on, computing a fit
nobody waits for and holding the daemon's log pipe open. :func:`exit_with_parent`, called in the
worker's initializer, starts a thread that checks the parent every ``poll_s`` and kills its own
process (SIGKILL: nothing of a worker needs cleaning up) once the parent is no longer the one that
started it.
"""

from __future__ import annotations

import os
import signal
import threading
import time

__all__ = ["PARENT_POLL_S", "exit_with_parent"]

PARENT_POLL_S = 0.5


def _watch(parent_pid: int, poll_s: float) -> None:
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os.kill(os.getpid(), signal.SIGKILL)


def exit_with_parent(parent_pid: int, poll_s: float = PARENT_POLL_S) -> None:
    """End this process within ``poll_s`` of process ``parent_pid`` (its parent) ending.

    ``parent_pid`` is given by the parent (``os.getpid()`` there), so a parent that ended before
    this call is noticed at once.
    """
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_watch, args=(parent_pid, poll_s), name="parent-watch", daemon=True).start()
