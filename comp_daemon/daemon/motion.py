"""Motion ports: how the daemon tells the robot where to go.

:class:`LineMotionPort` speaks a one-line request/answer protocol over TCP::

    move A1 A2 A3 A4 A5 A6      (deg, controller axis values)
    → OK …                      once the robot has taken (and, on the simulated cell, finished) the move
    → ERR <reason>              refused (limits, a motion already running) or aborted (robot stopped)

The simulated controller's command port answers it (:mod:`comp_daemon.sim.rsi_controller`); on a
line, a cell gateway does (e.g. a KRL program with an EKI channel that reads the axis values into a
``PTP`` target and answers after ``$ADVANCE`` has been reached) — see docs/daemon.md. Each move uses
a fresh connection, so a cancelled request can never leave an unread answer for the next one.
"""

from __future__ import annotations

from collections.abc import Sequence

from comp_daemon.rt.executor import MotionError
from comp_daemon.sim_client import line_command

__all__ = ["LineMotionPort"]


class LineMotionPort:
    """A :class:`comp_daemon.rt.executor.MotionPort` over the line protocol above."""

    def __init__(self, host: str, port: int, *, timeout_s: float = 120.0) -> None:
        self.host = host
        self.port = port
        self.timeout_s = timeout_s
        self.moves = 0

    async def move_to(self, axes_deg: Sequence[float]) -> None:
        if len(axes_deg) != 6:
            raise MotionError(f"a move needs 6 axis values, got {len(axes_deg)}")
        line = "move " + " ".join(f"{float(a):.6f}" for a in axes_deg)
        self.moves += 1
        try:
            await line_command(self.host, self.port, line, timeout_s=self.timeout_s)
        except TimeoutError:
            raise MotionError(f"no answer from the motion port within {self.timeout_s} s") from None
        except OSError as exc:
            raise MotionError(f"motion port {self.host}:{self.port}: {exc}") from None
        except RuntimeError as exc:
            raise MotionError(str(exc)) from None
