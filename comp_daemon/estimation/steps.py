"""The steps of a long fit, for whoever shows its progress (the terminal, a daemon job).

The numerics call :func:`report` between their steps — what they are doing, how many steps are
done and how many there are in all as far as they know — and know nothing of who listens. A door
that shows progress listens for the duration of a call with :func:`listening` (a context
variable: each thread or task has its own listener, and none by default). Without a listener a
report costs one lookup.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

__all__ = ["StepListener", "listening", "report"]

StepListener = Callable[[str, int, int], None]  # (what, done, total)

_listener: ContextVar[StepListener | None] = ContextVar("comp_daemon_fit_steps", default=None)


def report(what: str, done: int, total: int) -> None:
    """Tell the listener, if any, that ``done`` of ``total`` steps of ``what`` are done."""
    listener = _listener.get()
    if listener is not None:
        listener(what, done, total)


@contextmanager
def listening(listener: StepListener) -> Iterator[None]:
    """Hand the reports made inside the block to ``listener``."""
    token = _listener.set(listener)
    try:
        yield
    finally:
        _listener.reset(token)
