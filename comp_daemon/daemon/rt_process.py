"""The daemon's side of the real-time process: start it, command the loop, mirror what it reports.

The RSI endpoint, the grating readers and the loop run in a child process
(:mod:`comp_daemon.rt.child`, started as ``python -m comp_daemon.rt.child``) so that a reply never
waits for the daemon's interpreter. This module is how the daemon reaches them:

- :class:`RealtimeProcess` starts the child with one end of a socket pair, carries requests
  (open the RSI endpoint, start the readers and the loop, sample cycles, close, stop) and commands
  over it (:mod:`comp_daemon.rt.link`), applies the child's state reports and relays its log
  records under their own logger names;
- :class:`RemoteRuntime` is a :class:`~comp_daemon.rt.loop.LoopView` kept current by the reports,
  with the commands of ``LoopRuntime``. A command is checked against the mirrored core state with
  the same pure function the child applies (so ``arm`` raises at once where the loop would refuse),
  sent, and applied to the mirror; reports older than the last command do not overwrite the
  mirrored core. When the child has gone, the active target is reported faulted here;
- :class:`ReaderMirror` is a grating reader as the child last reported it.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import socket
import sys
import time
from array import array
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from comp_daemon.common.logs import get_logger
from comp_daemon.rt.encoder_reader import EncoderFault, EncoderReading
from comp_daemon.rt.encoder_reader import FaultKind as EncoderFaultKind
from comp_daemon.rt.grating_cal import GratingCalibration
from comp_daemon.rt.link import RSI_COUNTERS, LinkProtocol, LoopStart, RtProcessError, RtStart, StateReport
from comp_daemon.rt.loop import CycleSample, LoopView
from comp_daemon.rt.rsi_server import RsiServerStats
from comp_daemon.rt.safety import Event, Faulted, FaultKind, arm, fault, release, reset, shutdown

__all__ = ["ReaderMirror", "RealtimeProcess", "RemoteRuntime", "RtProcessError"]

log = get_logger(__name__)

#: how the daemon starts the child
CHILD_MODULE = "comp_daemon.rt.child"


class ReaderMirror:
    """A grating reader as the child last reported it (a ``FeedbackSource`` of the loop view)."""

    def __init__(self, joint: int, stale_after_ms: float, clock_ns: Callable[[], int]) -> None:
        self.joint = joint
        self.stale_after_ns = int(stale_after_ms * 1e6)
        self.clock_ns = clock_ns
        self.fault_counts: dict[EncoderFaultKind, int] = dict.fromkeys(EncoderFaultKind, 0)
        self.warnings = 0
        self._latest: EncoderReading | EncoderFault = EncoderFault(
            joint, EncoderFaultKind.NO_DATA, "no report from the real-time process yet", None
        )
        self._at_ns = clock_ns()

    def update(self, reading: EncoderReading | EncoderFault, at_ns: int) -> None:
        self._latest, self._at_ns = reading, at_ns

    def reading(self, now_ns: int | None = None) -> EncoderReading | EncoderFault:
        now = self.clock_ns() if now_ns is None else now_ns
        r = self._latest
        if isinstance(r, EncoderReading):
            age = now - r.t_ns
            if age > self.stale_after_ns:
                return EncoderFault(
                    self.joint,
                    EncoderFaultKind.STALE,
                    f"latest reported reading is {age / 1e6:.1f} ms old",
                    age,
                )
            return replace(r, age_ns=age)
        if r.last_good_age_ns is None:
            return r
        return replace(r, last_good_age_ns=r.last_good_age_ns + max(0, now - self._at_ns))


class RemoteRuntime(LoopView):
    """The loop in the real-time process, seen and commanded from the daemon. See the module docstring."""

    #: set by RealtimeProcess.start_loop (a class default: LoopView.__init__ calls set_calibration first)
    process: RealtimeProcess | None = None

    def _post_init(self) -> None:
        self._sent = 0  # sequence number of the last command sent
        self._mirrors = {s.joint: s for s in self.sources if isinstance(s, ReaderMirror)}

    # ---------------------------------------------------------------------------- reports

    def apply(self, report: StateReport) -> None:
        if report.applied >= self._sent:
            self.core = report.core
        self.telegrams = report.telegrams
        self.last_ipoc = report.last_ipoc
        self.last_actual_deg = report.last_actual_deg
        self.last_setpoint_deg = report.last_setpoint_deg
        self.last_angles_deg = report.last_angles_deg
        self.last_stop = report.last_stop
        self.last_ak_deg = report.last_ak_deg
        self.replies_after_shutdown = report.replies_after_shutdown
        self._last_rx_ns = report.last_rx_ns
        self.last_feedback = report.readings
        mirrors = self._mirrors
        for r in report.readings:
            if r.joint in mirrors:
                mirrors[r.joint].update(r, report.now_ns)
        for joint, counts, warnings in report.reader_counts:
            if joint in mirrors:
                mirrors[joint].fault_counts, mirrors[joint].warnings = counts, warnings
        self.trace.extend(report.trace)
        for f in report.faults:
            self._log_fault(f)

    def on_event(self, event: Event) -> None:
        self.events.put_nowait(event)

    def on_lost(self, reason: str) -> None:
        """The child has gone: the active target is reported faulted here (nobody else can)."""
        result = fault(
            self.core, FaultKind.RSI_LOST, f"the real-time process has gone ({reason})", self.now_s()
        )
        self.core = result.core
        for event in result.events:
            if isinstance(event, Faulted):
                self._log_fault(event.fault)
            self.events.put_nowait(event)

    # ---------------------------------------------------------------------------- commands

    def _send(self, name: str, *args: Any, required: bool = False) -> None:
        """Send a command. With the child gone only a required one raises: release, reset and
        shutdown have nothing left to act on (the child went safe when it lost the daemon)."""
        try:
            if self.process is None:
                raise RtProcessError("the real-time process is not started")
            self._sent = self.process.command(name, *args)
        except RtProcessError:
            if required:
                raise
            log.warning(f"rt: {name} not sent: the real-time process has gone")

    def arm(self, target_id: str, commanded_deg: Sequence[float], loop_target_deg: Sequence[float]) -> None:
        # the same check the child makes: raises at once where the loop would refuse
        armed = arm(self.core, target_id, commanded_deg, loop_target_deg, self.now_s())
        self._send("arm", target_id, tuple(commanded_deg), tuple(loop_target_deg), required=True)
        self.core = armed

    def release(self) -> None:
        self.core = release(self.core)
        self._send("release")

    def reset(self) -> None:
        """Operator acknowledgement of a fault."""
        self.core = reset(self.core)
        self._send("reset")

    def fault(self, kind: FaultKind, detail: str) -> None:
        faulted = fault(self.core, kind, detail, self.now_s()).core  # its events come from the child
        self._send("fault", kind, detail, required=True)
        self.core = faulted

    def shutdown(self) -> None:
        """Zero steps and ``Stop = 1`` from the next telegram on; the active target is reported."""
        self.core = shutdown(self.core, self.now_s()).core
        self._send("shutdown")

    def set_calibration(self, calibration: GratingCalibration | None) -> None:
        super().set_calibration(calibration)
        if self.process is not None:  # None during LoopView.__init__: the child has it from LoopStart
            self._send("set_calibration", calibration)

    def readiness_reasons(self) -> list[str]:
        reasons = super().readiness_reasons()
        process = self.process
        if process is None or not process.alive:
            lost = None if process is None else process.lost_reason
            reasons.insert(0, f"the real-time process has gone ({lost or 'not running'})")
        return reasons

    async def next_event(self) -> Event:
        return await self.events.get()

    async def samples(self, n: int, timeout_s: float) -> list[CycleSample]:
        """The next ``n`` telegrams' axis values and raw grating counts; TimeoutError if they do not come."""
        if self.process is None:
            raise RtProcessError("the real-time process is not started")
        value: list[CycleSample] = await self.process.request(
            "samples", n, timeout_s, timeout_s=timeout_s + 5.0
        )
        return value


class RealtimeProcess:
    """Starts the child, carries requests and commands to it, mirrors what it reports, stops it."""

    def __init__(
        self,
        start: RtStart,
        *,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
        on_lost: Callable[[str], None] | None = None,
    ) -> None:
        self.start_cfg = start
        self.clock_ns = clock_ns
        self.on_lost = on_lost
        self.proc: asyncio.subprocess.Process | None = None
        self.link = LinkProtocol(self._on_message, self._on_link_lost)
        self.info: dict[str, Any] = {}
        self.rsi_stats = RsiServerStats(start.rsi.samples)
        self.runtime: RemoteRuntime | None = None
        self.readers: dict[int, ReaderMirror] = {}
        self.last_report_ns: int | None = None
        self.stopping = False
        self.lost_reason: str | None = None
        self._seq = 0
        self._req = itertools.count(1)
        self._pending: dict[int, asyncio.Future[Any]] = {}

    # ---------------------------------------------------------------------------- life cycle

    async def start(self) -> tuple[str, int]:
        """Start the child, open the RSI endpoint there; returns its address."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.proc = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                CHILD_MODULE,
                "--fd",
                str(theirs.fileno()),
                pass_fds=(theirs.fileno(),),
                stdin=asyncio.subprocess.DEVNULL,
            )
        finally:
            theirs.close()
        await asyncio.get_running_loop().create_unix_connection(lambda: self.link, sock=ours)
        self.info = await self.request("rsi", self.start_cfg, timeout_s=30.0)
        host, port = self.info["rsi_address"]
        return str(host), int(port)

    async def start_loop(self, spec: LoopStart) -> RemoteRuntime:
        """Start the readers and the loop in the child; returns the daemon's view of the loop."""
        # the child judges each reading's age itself; the mirror's copy is up to one report older
        lag_ms = self.start_cfg.push_period_s * 1e3
        self.readers = {
            rcfg.joint: ReaderMirror(rcfg.joint, rcfg.stale_after_ms + lag_ms, self.clock_ns)
            for rcfg, _ in spec.readers
        }
        runtime = spec.build(RemoteRuntime, self.readers, self.clock_ns)
        runtime.process = self
        self.runtime = runtime
        await self.request("loop", spec, timeout_s=30.0)
        return runtime

    async def close_rsi(self, grace_cycles: int) -> None:
        """The child replies with ``Stop = 1`` for ``grace_cycles`` telegrams (it counts them where
        they are handled), reports its final state, then closes the endpoint."""
        await self.request("close_rsi", grace_cycles, timeout_s=5.0)

    async def stop(self, timeout_s: float = 10.0) -> int | None:
        """Stop the readers and the child; returns its exit code. Idempotent."""
        self.stopping = True
        if self.link.connected:
            with contextlib.suppress(RtProcessError, TimeoutError):
                await self.request("stop", timeout_s=timeout_s / 2)
        proc = self.proc
        if proc is None:
            return None
        try:
            async with asyncio.timeout(timeout_s / 2):
                code = await proc.wait()
        except TimeoutError:
            log.error("rt: the real-time process did not exit; killing it")
            proc.kill()
            code = await proc.wait()
        self.link.close()
        return code

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.returncode is None and self.link.connected

    def report_age_s(self) -> float | None:
        last = self.last_report_ns
        return None if last is None else (self.clock_ns() - last) * 1e-9

    # ---------------------------------------------------------------------------- requests

    def command(self, name: str, *args: Any) -> int:
        """Send a command (no reply); returns its sequence number. RtProcessError if the child has gone."""
        self._seq += 1
        if not self.link.send(("cmd", self._seq, name, args)):
            raise RtProcessError(f"the real-time process has gone ({self.lost_reason or 'not started'})")
        return self._seq

    async def request(self, name: str, *args: Any, timeout_s: float) -> Any:
        req = next(self._req)
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[req] = fut
        try:
            if not self.link.send(("req", req, name, args)):
                raise RtProcessError(f"the real-time process has gone ({self.lost_reason or 'not started'})")
            async with asyncio.timeout(timeout_s):
                ok, value = await fut
        finally:
            self._pending.pop(req, None)
        if ok:
            return value
        kind, text = value
        if kind == "TimeoutError":
            raise TimeoutError(text)
        raise RtProcessError(f"the real-time process refused {name}: {kind}: {text}")

    # ---------------------------------------------------------------------------- messages

    def _on_message(self, message: Any) -> None:
        kind = message[0]
        if kind == "state":
            self._on_report(message[1])
        elif kind == "event":
            if self.runtime is not None:
                self.runtime.on_event(message[1])
        elif kind == "log":
            _, name, level, text = message
            # the child's record, re-emitted into this process's standard-library tree under its
            # own logger name (where the structlog renderer and any test's caplog see it)
            logging.getLogger(name).log(level, "%s", text)
        elif kind == "reply":
            _, req, ok, value = message
            fut = self._pending.get(req)
            if fut is not None and not fut.done():
                fut.set_result((ok, value))
        else:
            log.error(f"rt: unknown message {kind!r} from the real-time process")

    def _on_report(self, report: StateReport) -> None:
        self.last_report_ns = report.now_ns
        stats = self.rsi_stats
        for name, value in zip(RSI_COUNTERS, report.rsi_counters, strict=True):
            setattr(stats, name, value)
        for value in array("q", report.latency_ns):
            stats.latency.record(value)
        for value in array("q", report.jitter_ns):
            stats.jitter.record(value)
        if self.runtime is not None:
            self.runtime.apply(report)

    def _on_link_lost(self, exc: Exception | None) -> None:
        self.lost_reason = str(exc) if exc is not None else "its end of the link closed"
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(RtProcessError(f"the real-time process has gone ({self.lost_reason})"))
        if not self.stopping:
            log.error(f"rt: the real-time process has gone ({self.lost_reason})")
            if self.runtime is not None:
                self.runtime.on_lost(self.lost_reason)
            if self.on_lost is not None:
                self.on_lost(self.lost_reason)

    def describe(self) -> dict[str, Any]:
        info = self.info
        return {
            "pid": info.get("pid"),
            "cpu": info.get("cpu"),
            "scheduler": info.get("scheduler", "normal"),
            "cpu_wakeup_latency_us": info.get("cpu_wakeup_latency_us"),
            "notes": list(info.get("notes", ())),
        }
