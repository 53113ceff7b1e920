"""RSI sessions as the daemon sees them: each stop with its cause, each restart.

The robot controller is the RSI client, so the daemon learns of a stop only from the wire:
telegrams cease. :class:`RsiSessions` watches the loop (:meth:`RsiSessions.observe`, a few times a
second, while the real-time process's reports are current) and, when telegrams have ceased
(``rsi_alive`` false), records an :class:`RsiStopRecord`:
when the last telegram came, the cause, how many cycles the session answered and how many late
replies it had, and what happens next. The cause is read from what was on the wire:

- ``operator``: the daemon itself was shutting down (it sent ``Stop = 1``), or the robot program
  ended RSI (``RSI_OFF``, known from the simulated controller);
- ``fault``: the daemon's loop had latched a fault with the *stop* reaction and answered
  ``Stop = 1`` (the fault's kind and detail are kept), or the controller stopped on a correction
  monitor (AXISCORRMON);
- ``late_replies``: the controller's late-reply count (``Delay`` in its last telegram) had reached
  ``timeout_count − 1``: its next late reply hit the ETHERNET object's Timeout;
- ``timeout``: telegrams ceased with none of the above (program stopped, E-stop, network).

With the simulated cell, the controller's own stop message (its ``status``) replaces the guess, as
an operator reads the smartPAD's message window. When telegrams come again the stop gets its
re-arm (``rearmed_at``, the pause) and a new session begins. Every stop and re-arm goes to the
store's event log (``rsi.stopped``, ``rsi.rearmed``) and to the metrics; :meth:`RsiSessions.report`
is what ``/api/status`` shows under ``rsi``.

A controller that restarts faster than telegrams are seen to cease (a new source port, or its IPOC
gone back) is recognised by the RSI endpoint (:mod:`comp_daemon.rt.rsi_server`: its ``sessions``
count rises): the old session is recorded as stopped (``timeout``: its telegrams ceased) and
re-armed at once, the new one counted, and ``rsi.restarted`` written to the event log with both
senders. The endpoint's counts of older copies it did not answer (``stale``) and of telegrams from a
second sender it ignored (``other_sender``) go to the metrics as rejected datagrams
(``stale_copy``, ``other_sender``) and to the report.

Times are UNIX seconds (``time``) for the record and the daemon's monotonic ns clock for ages.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

from comp_daemon.common.logs import get_logger
from comp_daemon.daemon.realtime import Realtime
from comp_daemon.rt.loop import LoopView
from comp_daemon.rt.rsi_server import RsiServerStats
from comp_daemon.rt.safety import SafetyState
from comp_daemon.service import metrics

__all__ = ["STOP_CAUSES", "RsiSessions", "RsiStopRecord", "StopCauseWord"]

log = get_logger(__name__)

StopCauseWord = Literal["late_replies", "timeout", "fault", "operator"]
STOP_CAUSES: tuple[StopCauseWord, ...] = ("late_replies", "timeout", "fault", "operator")

#: the simulated controller's stop causes (``comp_daemon.sim.rsi_controller.StopCause``) in the daemon's words
_CONTROLLER_CAUSE: dict[str, StopCauseWord] = {
    "late_replies": "late_replies",
    "sensor_stop": "fault",
    "axiscorrmon": "fault",
    "internal_error": "fault",
    "rsi_off": "operator",
    "shutdown": "operator",
}

#: what an operator does on a real robot after each kind of stop
OPERATOR_ACTION: dict[StopCauseWord, str] = {
    "late_replies": "on the robot: acknowledge the RSI message on the smartPAD and start the program "
    "again (RSI_ON); the loop answers at once. Repeated late-reply stops: see docs/daemon.md "
    "(real-time CPU, load)",
    "timeout": "check the robot controller (program stopped, E-stop, messages) and the network, then "
    "start the program again (RSI_ON)",
    "fault": "acknowledge the fault here (Reset fault) once its cause is cleared, then start the "
    "program again on the robot (RSI_ON)",
    "operator": "start the program again on the robot (RSI_ON) when the cell is to run",
}


@dataclass(frozen=True, slots=True)
class RsiStopRecord:
    """One RSI stop as the daemon recorded it (``time``: last telegram, UNIX s)."""

    session: int
    time: float
    cause: StopCauseWord
    detail: str
    cycles: int  # telegrams answered in the session
    late_replies: int  # late replies in the session: the controller's count (Delay), else the daemon's
    last_ipoc: int | None
    next: str  # what happens next: the re-arm, or what the operator must do
    rearmed_at: float | None = None
    pause_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


ControllerStatus = Callable[[], Awaitable[dict[str, Any]]]


class RsiSessions:
    """Tracks RSI sessions and stops; see the module docstring."""

    def __init__(
        self,
        *,
        timeout_count: int,
        controller_status: ControllerStatus | None = None,
        record_event: Callable[[str, dict[str, Any]], Awaitable[None]] | None = None,
        wall_clock: Callable[[], float] = time.time,
        keep: int = 50,
        max_report_age_s: float = 0.25,
    ) -> None:
        """``controller_status``: the simulated controller's ``status`` (None on a real robot);
        ``record_event(kind, message)``: writes to the store's event log."""
        self.timeout_count = timeout_count
        self.controller_status = controller_status
        self.record_event = record_event
        self.wall_clock = wall_clock
        self.max_report_age_s = max_report_age_s
        self.sessions = 0
        self.rearms = 0
        self.running = False
        self.stops: deque[RsiStopRecord] = deque(maxlen=keep)
        self.stop_counts: dict[StopCauseWord, int] = dict.fromkeys(STOP_CAUSES, 0)
        self.rearm_after_s: float | None = None  # the simulated controller's pause, once known
        self._start_answered = 0  # stats.answered at the end of the previous session
        self._start_late = 0
        self.restarts = 0  # sessions the controller began without a stop seen in between
        self._endpoint_sessions = 0  # the endpoint's session count, as far as judged here
        self._rejected = {"stale_copy": 0, "other_sender": 0}
        self.sender: str | None = None  # the current session's sender, host:port

    async def watch(self, realtime: Realtime, period_s: float = 0.1) -> None:
        """Observe the real-time process's loop every ``period_s`` until cancelled (the daemon's
        own stop is recorded as ``daemon.stopped``, not as an RSI stop)."""
        while True:
            await asyncio.sleep(period_s)
            runtime, stats = realtime.runtime, realtime.rsi_stats
            if runtime is None or stats is None or realtime.process is None:
                continue
            try:
                await self.observe(runtime, stats, report_age_s=realtime.report_age_s())
            except Exception:  # a recording failure must not end the watch
                log.exception("daemon: recording the RSI session failed")

    async def observe(
        self, runtime: LoopView, stats: RsiServerStats, *, report_age_s: float | None = 0.0
    ) -> None:
        """Record a stop when telegrams have ceased since the last look, a re-arm when they came back.

        ``report_age_s``: how old the real-time process's latest report is; older than
        ``max_report_age_s`` (or None) the daemon's view of the telegrams is not current (that
        process was not scheduled, or is gone) and nothing is judged until it is."""
        self._count_rejected(stats)
        if report_age_s is None or report_age_s > self.max_report_age_s:
            return
        alive = runtime.rsi_alive()
        if alive and self.running and stats.sessions > self._endpoint_sessions:
            await self._restarted(runtime, stats)
        elif alive and not self.running:
            # telegrams that waited in the socket while the real-time process was not scheduled
            # arrive after the stop; the simulated controller says whether a session really runs
            simulated = self.controller_status is not None
            if self.stops and simulated and await self._controller_word() != "running":
                return
            await self._started(stats)
        elif self.running and not alive:
            await self._stopped(runtime, stats)

    def _count_rejected(self, stats: RsiServerStats) -> None:
        for reason, value in (("stale_copy", stats.stale), ("other_sender", stats.other_sender)):
            new = value - self._rejected[reason]
            if new > 0:
                metrics.RSI_REJECTED.labels(reason=reason).inc(new)
            self._rejected[reason] = value

    async def _restarted(self, runtime: LoopView, stats: RsiServerStats) -> None:
        """The endpoint saw a new controller session while telegrams never ceased long enough to be
        judged a stop: the old session ends (``timeout``) and the new one begins at the same moment."""
        now = self.wall_clock()
        before, self.sender = self.sender, stats.session_sender
        self._endpoint_sessions = stats.sessions
        detail = (
            f"the controller restarted: telegrams now come from {self.sender} "
            f"(endpoint session {stats.sessions}), the previous session's from {before}"
        )
        record = RsiStopRecord(
            session=self.sessions,
            time=round(now, 3),
            cause="timeout",
            detail=detail,
            cycles=stats.answered - self._start_answered,
            late_replies=stats.late - self._start_late,
            last_ipoc=runtime.last_ipoc,
            next="the new session runs",
            rearmed_at=round(now, 3),
            pause_s=0.0,
        )
        self.stops.append(record)
        self._start_answered, self._start_late = stats.answered, stats.late
        self.stop_counts["timeout"] += 1
        metrics.RSI_STOPS.labels(cause="timeout").inc()
        self.sessions += 1
        self.restarts += 1
        metrics.RSI_SESSIONS.inc()
        log.warning(f"rsi: session {self.sessions} started: {detail}")
        await self._record(
            "rsi.restarted",
            {
                "session": self.sessions,
                "sender": self.sender,
                "previous_sender": before,
                "stop": record.to_dict(),
            },
        )

    async def _started(self, stats: RsiServerStats) -> None:
        self._endpoint_sessions = stats.sessions
        self.sender = stats.session_sender
        self.running = True
        self.sessions += 1
        metrics.RSI_SESSIONS.inc()
        last = self.stops[-1] if self.stops else None
        if last is None or last.rearmed_at is not None:
            return
        self.rearms += 1
        now = self.wall_clock()
        pause = max(0.0, now - last.time)
        who = "the simulated controller" if self.controller_status is not None else "the robot controller"
        done = replace(
            last, rearmed_at=now, pause_s=round(pause, 3), next=f"{who} re-armed RSI after {pause:.1f} s"
        )
        self.stops[-1] = done
        log.info(f"rsi: session {self.sessions} started, {pause:.1f} s after the stop ({last.cause})")
        await self._record("rsi.rearmed", {"session": self.sessions, "after_stop": done.to_dict()})

    async def _stopped(self, runtime: LoopView, stats: RsiServerStats) -> None:
        age_s = runtime.telegram_age_s()
        when = self.wall_clock() - (0.0 if age_s is None else age_s)
        cause, detail = self._cause_from_wire(runtime, stats)
        controller = await self._controller_word()
        if controller == "running":  # the simulated controller still sends: not a stop (yet)
            return
        self.running = False
        if controller is not None and runtime.core.state is not SafetyState.STOPPING:
            cause, detail = controller
        delay = stats.controller_delay
        late = delay if delay is not None else stats.late - self._start_late
        if cause == "late_replies":  # the stop came with the late reply that reached the Timeout
            late = max(late, self.timeout_count)
        record = RsiStopRecord(
            session=self.sessions,
            time=round(when, 3),
            cause=cause,
            detail=detail,
            cycles=stats.answered - self._start_answered,
            late_replies=late,
            last_ipoc=runtime.last_ipoc,
            next=self._next(cause, runtime),
        )
        self.stops.append(record)
        # every telegram after this stop belongs to the next session (none is answered in between)
        self._start_answered, self._start_late = stats.answered, stats.late
        self.stop_counts[cause] += 1
        metrics.RSI_STOPS.labels(cause=cause).inc()
        log.warning(f"rsi: RSI stopped after {record.cycles} cycles ({cause}: {detail}); next: {record.next}")
        await self._record("rsi.stopped", record.to_dict())

    def _cause_from_wire(self, runtime: LoopView, stats: RsiServerStats) -> tuple[StopCauseWord, str]:
        core = runtime.core
        if core.state is SafetyState.STOPPING:
            return "operator", "the daemon is shutting down (it answered Stop = 1)"
        if runtime.last_stop:
            f = core.fault
            what = "a fault" if f is None else f"{f.kind} ({f.reaction}): {f.detail}"
            return "fault", f"the daemon answered Stop = 1 after {what}"
        delay = stats.controller_delay
        if delay is not None and delay >= self.timeout_count - 1:
            return (
                "late_replies",
                f"the controller had counted {delay} late replies (Timeout at {self.timeout_count})",
            )
        return (
            "timeout",
            "telegrams ceased without Stop = 1 or a late-reply count near the controller's Timeout",
        )

    async def _controller_word(self) -> tuple[StopCauseWord, str] | Literal["running"] | None:
        """The simulated controller's own stop cause and message, ``"running"`` if it says RSI still
        runs, None without a simulated controller or an answer."""
        if self.controller_status is None:
            return None
        try:
            doc = await self.controller_status()
        except (OSError, RuntimeError, TimeoutError, ValueError) as exc:
            log.warning(f"rsi: could not ask the simulated controller why RSI stopped: {exc}")
            return None
        self.rearm_after_s = doc.get("rearm_after_s")
        if doc.get("state") == "running":
            return "running"
        cause = _CONTROLLER_CAUSE.get(str(doc.get("stop_cause")))
        if doc.get("state") != "stopped" or cause is None:
            return None
        return cause, f"controller: {doc.get('stop_reason')}"

    def _next(self, cause: StopCauseWord, runtime: LoopView) -> str:
        if runtime.core.state is SafetyState.STOPPING:
            return "none: the daemon is stopping"
        if self.controller_status is not None and self.rearm_after_s is not None and cause != "operator":
            text = f"the simulated controller re-arms RSI in {self.rearm_after_s:g} s"
            if runtime.core.state is SafetyState.FAULT:
                text += "; acknowledge the fault here (Reset fault) to take targets again"
            return text
        return OPERATOR_ACTION[cause]

    async def _record(self, kind: str, message: dict[str, Any]) -> None:
        if self.record_event is None:
            return
        try:
            await self.record_event(kind, message)
        except Exception:
            log.exception(f"rsi: could not record {kind}")

    def report(self) -> dict[str, Any]:
        """What ``/api/status`` shows under ``rsi``: sessions, stops by cause, the stops (newest first)."""
        last = self.stops[-1] if self.stops else None
        return {
            "running": self.running,
            "sessions": self.sessions,
            "stops_total": sum(self.stop_counts.values()),
            "stops_by_cause": dict(self.stop_counts),
            "rearms": self.rearms,
            "restarts": self.restarts,
            "sender": self.sender,
            "stale_copies": self._rejected["stale_copy"],
            "other_sender": self._rejected["other_sender"],
            "rearm_after_s": self.rearm_after_s,
            "next": None if self.running or last is None else last.next,
            "stops": [s.to_dict() for s in reversed(self.stops)],
        }
