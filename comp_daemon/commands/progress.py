"""Progress of the long commands (``evaluate``, ``fit``, ``diagnose``) on stderr, drawn by rich.

:func:`progress` opens one task, :func:`tracked` one over the items of a loop: with a total, a bar
with ``done/total`` and the elapsed time; without one, a spinner and the elapsed time (a single fit
or a diagnosis reports no steps of its own). The display is drawn only when stderr is a terminal:
piped or redirected to a file, stderr gets nothing from here (whatever ``FORCE_COLOR`` or
``TTY_COMPATIBLE`` say), so logs and scripts see only the command's own messages. It is cleared
when the task ends; :meth:`Steps.log` lines stay above it. The numerics know nothing of it: the
commands advance it between their calls, and the steps a fit reports while it runs
(:mod:`comp_daemon.estimation.steps`: its cross-validation fits, its candidates) follow the task's
description ("fitting chebyshev:cv on 700 rows (7 of 15, 8 after it): cross-validation fits 12 of
50").
"""

from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TextIO, TypeVar

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
)

from comp_daemon.estimation.steps import listening

__all__ = ["Steps", "progress", "tracked"]

T = TypeVar("T")


class Steps:
    """The handle of one running task: advance it, say what it is doing, leave a line above it."""

    def __init__(self, bar: Progress, task: TaskID, description: str = "") -> None:
        self._bar = bar
        self._task = task
        self._description = description

    def note(self, description: str) -> None:
        """Show ``description`` as what the task is doing now (drawn at once: a step shorter than the
        display's refresh period is still seen)."""
        self._description = description
        self._bar.update(self._task, description=description, refresh=True)

    def step(self, what: str, done: int, total: int) -> None:
        """A step of the fit running now, after the task's description (a
        :data:`comp_daemon.estimation.steps.StepListener`)."""
        if not self._bar.disable:
            self._bar.update(self._task, description=f"{self._description}: {what} {done} of {total}")

    def advance(self, steps: int = 1) -> None:
        self._bar.advance(self._task, steps)

    def log(self, line: str) -> None:
        """Print ``line`` above the display (only where the display is drawn)."""
        if not self._bar.disable:
            self._bar.console.print(line, highlight=False, markup=False)


@contextmanager
def progress(description: str, total: int | None = None, stream: TextIO | None = None) -> Iterator[Steps]:
    """A progress display for one task on ``stream`` (default: ``sys.stderr`` at the call),
    drawn only when that is a terminal (module docstring)."""
    out = sys.stderr if stream is None else stream
    try:
        tty = bool(out.isatty())
    except (AttributeError, ValueError):
        tty = False
    console = Console(file=out, force_terminal=tty)
    columns = [SpinnerColumn(), TextColumn("{task.description}"), BarColumn()]
    if total is not None:
        columns.append(MofNCompleteColumn())
    with Progress(*columns, TimeElapsedColumn(), console=console, disable=not tty, transient=True) as bar:
        handle = Steps(bar, bar.add_task(description, total=total), description)
        with listening(handle.step):
            yield handle


def tracked(items: Sequence[T], description: str) -> Iterator[tuple[Steps, T]]:
    """Each of ``items`` with the :class:`Steps` of one task over all of them, advanced after each
    (``for steps, item in tracked(items, "…"):``); the display ends with the loop."""
    with progress(description, total=len(items)) as steps:
        for item in items:
            yield steps, item
            steps.advance()
