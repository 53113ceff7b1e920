"""The loop: the RSI handler, the commands that steer it, and what the daemon may see of it.

:meth:`LoopRuntime.handle` is the synchronous handler the RSI server calls in its receive callback.
Per telegram it reads the latest grating reading of each controlled joint (an O(1) look-up in the
encoder readers, which poll on their own tasks), maps counts to joint angles with the active
grating calibration, runs one step of the safety machine and controller
(:func:`comp_daemon.rt.safety.on_cycle`) and returns the ``<Sen>`` reply. Nothing on that path
awaits, allocates beyond a few small tuples, or touches a file, a socket other than the reply's,
or a lock. Events for the executor (arrived, settled, faulted) go to an ``asyncio.Queue`` with
``put_nowait``.

Where it runs: in the real-time process (:mod:`comp_daemon.rt.child`), on that process's one event
loop — the handler in the RSI endpoint's receive callback, the commands (:meth:`arm`,
:meth:`release`, :meth:`reset`, :meth:`fault`, :meth:`shutdown`, :meth:`set_calibration`) as the
daemon's messages arrive, :meth:`tick` on a timer. One thread, so no locks: each command and each
telegram is a read-modify-write of the frozen core state that no other callback interrupts, and
commands keep their synchronous meaning (``arm`` raises when the loop refuses). The daemon sees the
loop through :class:`LoopView` (its :class:`~comp_daemon.daemon.rt_process.RemoteRuntime` is one).

Units: angles in deg (controller axis values); the clock is integer ns (``time.perf_counter_ns``),
shared with the encoder readers so reading ages compare directly.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import EncoderFault, EncoderReading
from comp_daemon.rt.encoder_reader import FaultKind as EncoderFaultKind
from comp_daemon.rt.grating_cal import GratingCalibration, JointGratingMap
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply
from comp_daemon.rt.safety import (
    CycleInput,
    Event,
    Fault,
    FaultKind,
    FeedbackFault,
    LoopCore,
    Reading,
    SafetySettings,
    SafetyState,
    arm,
    fault,
    new_core,
    on_cycle,
    on_tick,
    release,
    reset,
    shutdown,
)

__all__ = ["CycleSample", "FeedbackSource", "LoopRuntime", "LoopView"]

Clock = Callable[[], int]

_STALE_KINDS = frozenset({EncoderFaultKind.STALE, EncoderFaultKind.SILENT, EncoderFaultKind.NO_DATA})


class FeedbackSource(Protocol):
    """A grating reader: the latest valid reading, or why there is none (O(1), no I/O)."""

    def reading(self, now_ns: int | None = None) -> EncoderReading | EncoderFault: ...


@dataclass(frozen=True, slots=True)
class CycleSample:
    """What one telegram showed: axis values (``AIPos``) and the raw counts of the gratings."""

    ipoc: int
    actual_deg: tuple[float, ...] | None
    setpoint_deg: tuple[float, ...] | None
    counts: tuple[int | None, ...]


class LoopView:
    """What the service may see of the loop: the core state, the last cycle, the gratings' health.

    :class:`LoopRuntime` keeps these attributes up to date as it handles telegrams; the real-time
    daemon's view (:class:`comp_daemon.daemon.rt_process.RemoteRuntime`) keeps them as the real-time
    process reports them. Joint numbers are 1-based (1 = A1) at this interface.
    """

    def __init__(
        self,
        sources: Mapping[int, FeedbackSource],
        *,
        calibration: GratingCalibration | None,
        safety: SafetySettings,
        loop: JointLoopSettings,
        sen_type: str = "ImFree",
        clock_ns: Clock = time.perf_counter_ns,
        rsi_alive_s: float = 0.5,
        trace_cycles: int = 4096,
    ) -> None:
        self.joints: tuple[int, ...] = tuple(sorted(sources))
        self.sources = tuple(sources[j] for j in self.joints)
        self.safety = safety
        self.loop = loop
        self.sen_type = sen_type
        self.clock_ns = clock_ns
        self.rsi_alive_s = rsi_alive_s
        self.core: LoopCore = new_core([j - 1 for j in self.joints])
        self._maps: tuple[JointGratingMap | None, ...] = (None,) * len(self.joints)
        self.calibration: GratingCalibration | None = None
        self.set_calibration(calibration)
        self.events: asyncio.Queue[Event] = asyncio.Queue()
        self.fault_log: deque[Fault] = deque(maxlen=64)
        self.faults_logged = 0  # how many faults fault_log has seen (it keeps the last 64)
        self.telegrams = 0
        self.last_ipoc: int | None = None
        self.last_actual_deg: tuple[float, ...] | None = None
        self.last_setpoint_deg: tuple[float, ...] | None = None
        self.last_angles_deg: tuple[float | None, ...] = (None,) * len(self.joints)
        self.last_feedback: tuple[EncoderReading | EncoderFault | None, ...] = (None,) * len(self.joints)
        self.last_stop = False
        self.last_ak_deg: tuple[float, ...] = (0.0,) * 6
        self.replies_after_shutdown = 0
        #: the last ``trace_cycles`` cycles: (t_ns, ipoc, state, target − grating per joint, AK sent)
        self.trace: deque[tuple[int, int, SafetyState, tuple[float, ...], tuple[float, ...]]] = deque(
            maxlen=trace_cycles
        )
        self._last_rx_ns: int | None = None
        self._post_init()

    def _post_init(self) -> None:
        """Subclasses set up their own state here (called last by ``__init__``)."""

    def _log_fault(self, f: Fault) -> None:
        self.fault_log.append(f)
        self.faults_logged += 1

    def now_s(self) -> float:
        return self.clock_ns() * 1e-9

    def set_calibration(self, calibration: GratingCalibration | None) -> None:
        """Use a (new) grating calibration from the next telegram on."""
        if calibration is None:
            self._maps = (None,) * len(self.joints)
        else:
            maps: list[JointGratingMap | None] = []
            for j in self.joints:
                try:
                    maps.append(calibration.for_joint(j))
                except KeyError:
                    maps.append(None)
            self._maps = tuple(maps)
        self.calibration = calibration

    # ------------------------------------------------------------------------------ views

    def next_telegram_ns(self) -> int | None:
        """When the next telegram is due (ns of the clock), from the last one and the cycle time;
        None before the first or when telegrams have stopped for more than four cycles."""
        last = self._last_rx_ns
        if last is None:
            return None
        cycle_ns = int(self.loop.cycle_s * 1e9)
        elapsed = self.clock_ns() - last
        if cycle_ns <= 0 or elapsed > 4 * cycle_ns:
            return None
        return last + max(1, -(-elapsed // cycle_ns)) * cycle_ns

    async def wait_stop_replies(
        self, n: int, cycle_s: float, quiet_s: float = 0.5, limit_s: float = 3.0
    ) -> None:
        """Wait until ``n`` replies with ``Stop = 1`` have gone out since the shutdown, or until the
        controller has sent nothing for ``max(n + 2 cycles, quiet_s)`` since the wait began or its
        last telegram, whichever is later (it stopped RSI, as a controller does on the first
        ``Stop = 1``, or RSI was not running), at most ``limit_s`` (how the shutdown lets the
        controller see ``Stop = 1`` before the endpoint closes).

        Replies and silence are both counted where the telegrams are handled, and the wait ends
        only when two looks half a cycle apart agree: telegrams that waited in the socket while
        this process was not scheduled (or stopped) are read in between, so a busy machine delays
        the wait and does not end it before the controller had its replies."""
        start = self.clock_ns()
        quiet_ns = int(max((n + 2) * cycle_s, quiet_s) * 1e9)
        end = start + int(limit_s * 1e9)
        ending = False
        while self.replies_after_shutdown < n:
            now, last = self.clock_ns(), self._last_rx_ns
            if now >= end or now - (start if last is None else max(start, last)) >= quiet_ns:
                if ending:
                    return
                ending = True
            else:
                ending = False
            await asyncio.sleep(cycle_s / 2)

    def telegram_age_s(self) -> float | None:
        """Seconds since the last telegram (None before the first)."""
        last = self._last_rx_ns
        return None if last is None else (self.clock_ns() - last) * 1e-9

    def rsi_alive(self) -> bool:
        last = self._last_rx_ns
        return last is not None and (self.clock_ns() - last) * 1e-9 <= self.rsi_alive_s

    def encoder_status(self, now_ns: int | None = None) -> list[tuple[int, EncoderReading | EncoderFault]]:
        now = self.clock_ns() if now_ns is None else now_ns
        return [(j, s.reading(now)) for j, s in zip(self.joints, self.sources, strict=True)]

    def readiness_reasons(self) -> list[str]:
        """Why a target cannot start now (empty when it can)."""
        reasons = []
        core = self.core
        if core.state is SafetyState.STOPPING:
            reasons.append("the daemon is shutting down")
        elif core.state is SafetyState.FAULT and core.stop and core.fault is not None:
            reasons.append(
                f"stop fault latched ({core.fault.kind}: {core.fault.detail}); an operator must reset it"
            )
        if not self.rsi_alive():
            reasons.append("no RSI telegrams from the robot controller")
        if self.calibration is None or any(m is None for m in self._maps):
            missing = [f"A{j}" for j, m in zip(self.joints, self._maps, strict=True) if m is None]
            reasons.append(f"no grating calibration for {', '.join(missing)}")
        for j, r in self.encoder_status():
            if isinstance(r, EncoderFault):
                reasons.append(f"grating A{j}: {r.kind} ({r.detail})")
        return reasons

    def joint_rows(self) -> list[dict[str, Any]]:
        """Per controlled joint: angle, target, error (grating − target), correction, encoder health."""
        core = self.core
        rows = []
        totals = core.total_correction_deg
        now = self.clock_ns()
        for i, (j, source) in enumerate(zip(self.joints, self.sources, strict=True)):
            r = source.reading(now)
            target = None if core.loop_target_deg is None else core.loop_target_deg[i]
            angle = self.last_angles_deg[i]
            err = core.errors_deg[i] if i < len(core.errors_deg) else math.nan
            rows.append(
                {
                    "joint": j,
                    "axis_deg": None if self.last_actual_deg is None else self.last_actual_deg[j - 1],
                    "target_deg": target,
                    "grating_deg": angle,
                    "error_deg": None if math.isnan(err) else -err,
                    "correction_deg": totals[j - 1],
                    "mode": core.loops[i].mode.value,
                    "encoder": "ok" if isinstance(r, EncoderReading) else str(r.kind),
                    "encoder_detail": None if isinstance(r, EncoderReading) else r.detail,
                    "reading_age_ms": r.age_ns / 1e6 if isinstance(r, EncoderReading) else None,
                }
            )
        return rows


class LoopRuntime(LoopView):
    """See the module docstring: the loop itself, handling telegrams in the RSI receive callback."""

    def _post_init(self) -> None:
        self._samplers: list[tuple[int, list[CycleSample], asyncio.Future[list[CycleSample]]]] = []

    # ------------------------------------------------------------------------------ the handler

    def handle(self, telegram: RobTelegram) -> SenReply:
        """One RSI cycle (called in the UDP receive callback)."""
        now_ns = self.clock_ns()
        feedback: list[Reading | FeedbackFault] = []
        angles: list[float | None] = []
        readings: list[EncoderReading | EncoderFault] = []
        for source, cal in zip(self.sources, self._maps, strict=True):
            r = source.reading(now_ns)
            readings.append(r)
            if isinstance(r, EncoderReading):
                if cal is None:
                    feedback.append(FeedbackFault(FaultKind.FEEDBACK_FAULT, "no grating calibration"))
                    angles.append(None)
                else:
                    angle = r.count * cal.slope_deg_per_count + cal.zero_deg
                    feedback.append((angle, r.t_ns * 1e-9))
                    angles.append(angle)
            else:
                kind = FaultKind.FEEDBACK_STALE if r.kind in _STALE_KINDS else FaultKind.FEEDBACK_FAULT
                feedback.append(FeedbackFault(kind, f"{r.kind}: {r.detail}"))
                angles.append(None)
        inp = CycleInput(
            now_ns * 1e-9, telegram.ipoc, telegram.aspos_deg, telegram.aipos_deg, tuple(feedback)
        )
        result = on_cycle(self.safety, self.loop, self.core, inp)
        self.core = result.core
        for event in result.events:
            self._event(event)
        self.telegrams += 1
        self.last_ipoc = telegram.ipoc
        self.last_actual_deg = telegram.aipos_deg
        self.last_setpoint_deg = telegram.aspos_deg
        self.last_angles_deg = tuple(angles)
        self.last_feedback = tuple(readings)
        self.last_stop = result.output.stop
        self.last_ak_deg = result.output.ak_deg
        self.trace.append(
            (now_ns, telegram.ipoc, self.core.state, self.core.errors_deg, result.output.ak_deg)
        )
        if self.core.state is SafetyState.STOPPING:
            self.replies_after_shutdown += 1
        self._last_rx_ns = now_ns
        if self._samplers:
            self._sample(telegram, readings)
        return SenReply(telegram.ipoc, result.output.ak_deg, result.output.stop, self.sen_type)

    def _event(self, event: Event) -> None:
        f = getattr(event, "fault", None)
        if isinstance(f, Fault):
            self._log_fault(f)
        self.events.put_nowait(event)

    def _sample(self, telegram: RobTelegram, readings: Sequence[EncoderReading | EncoderFault]) -> None:
        counts = tuple(r.count if isinstance(r, EncoderReading) else None for r in readings)
        sample = CycleSample(telegram.ipoc, telegram.aipos_deg, telegram.aspos_deg, counts)
        keep = []
        for n, bucket, fut in self._samplers:
            if fut.done():
                continue
            bucket.append(sample)
            if len(bucket) >= n:
                fut.set_result(bucket)
            else:
                keep.append((n, bucket, fut))
        self._samplers = keep

    # ------------------------------------------------------------------------------ commands

    def arm(self, target_id: str, commanded_deg: Sequence[float], loop_target_deg: Sequence[float]) -> None:
        self.core = arm(self.core, target_id, commanded_deg, loop_target_deg, self.now_s())

    def release(self) -> None:
        self.core = release(self.core)

    def reset(self) -> None:
        """Operator acknowledgement of a fault."""
        self.core = reset(self.core)

    def fault(self, kind: FaultKind, detail: str) -> None:
        result = fault(self.core, kind, detail, self.now_s())
        self.core = result.core
        for event in result.events:
            self._event(event)
        if result.core.fault is not None and not result.events:
            self._log_fault(result.core.fault)

    def new_session(self, what: str) -> None:
        """The controller began a new RSI session (it restarted): an active target is faulted
        (``rsi_lost``, freeze) before the new session's first telegram is handled, because the
        correction the restarted controller holds is no longer the one the loop has summed up."""
        if self.core.state in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED):
            self.fault(FaultKind.RSI_LOST, f"the controller began a new RSI session ({what})")

    def shutdown(self) -> None:
        """Zero steps and ``Stop = 1`` from the next telegram on; the active target is reported."""
        result = shutdown(self.core, self.now_s())
        self.core = result.core
        for event in result.events:
            self._event(event)

    def tick(self) -> None:
        """Timer check between telegrams (called a few times per second)."""
        result = on_tick(self.safety, self.core, self.now_s())
        if result.core is not self.core:
            self.core = result.core
            for event in result.events:
                self._event(event)

    async def next_event(self) -> Event:
        return await self.events.get()

    async def samples(self, n: int, timeout_s: float) -> list[CycleSample]:
        """The next ``n`` telegrams' axis values and raw grating counts (for the grating calibration).

        Raises TimeoutError when they do not arrive within ``timeout_s``.
        """
        fut: asyncio.Future[list[CycleSample]] = asyncio.get_running_loop().create_future()
        self._samplers.append((n, [], fut))
        try:
            async with asyncio.timeout(timeout_s):
                return await fut
        finally:
            fut.cancel()
