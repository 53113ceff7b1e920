"""The real-time process: the RSI endpoint, the grating readers and the loop in their own interpreter.

On one interpreter the RSI reply shares the GIL with the HTTP side: any C call that holds it (a
request body validated, a page of rows decoded, a collector pass) delays the reply by its length,
and under load that is what the slowest replies wait for (docs/benchmarks.md). This module moves the
whole real-time path into a child process (``[realtime] mode = "process"``, the default): the UDP
endpoint answering in its receive callback, one reader task per grating and the
:class:`~comp_daemon.daemon.runtime.LoopRuntime` — unchanged, on the child's own event loop — while
the daemon keeps the service, the executor and the store.

The child (``python -m comp_daemon.daemon.rt_process --fd N``):

- pins itself to ``[realtime] cpu`` and takes ``SCHED_FIFO`` at ``[realtime] priority`` where
  permitted, holds the PM QoS request, freezes its start-up objects out of the collector's sight;
- runs the loop's timers itself (``tick``), so a stalled daemon cannot keep a move timeout or a lost
  RSI connection from faulting the loop;
- reports to the daemon over a socket pair (:mod:`comp_daemon.daemon.rt_link`): every safety event
  at once, a state report (core state, last cycle, grating readings, RSI counters and the new
  latency samples) after a reply every ``push_period_s``, and its log records;
- goes safe on its own when the daemon has gone (the socket closes, whatever killed the daemon) or
  on SIGTERM: zero steps and ``Stop = 1`` for the grace cycles, then it closes the endpoint and
  exits. SIGINT is left to the daemon, which orders the shutdown.

The daemon's side is :class:`RealtimeProcess` (start, requests, stop) and :class:`RemoteRuntime`, a
:class:`~comp_daemon.daemon.runtime.LoopView` kept current by the reports, with the commands of
``LoopRuntime``. A command is checked against the mirrored core state with the same pure function
the child applies (so ``arm`` raises at once where the loop would refuse), sent, and applied to the
mirror; reports older than the last command do not overwrite the mirrored core. Should the child
refuse a target the mirror accepted (a fault latched in between), it reports ``Faulted`` for that
target, so the executor fails it with the reason.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import itertools
import logging
import os
import signal
import socket
import sys
import time
from array import array
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, BinaryIO, TypeVar

from comp_daemon.daemon.rt_link import LinkProtocol
from comp_daemon.daemon.runtime import CycleSample, FeedbackSource, LoopRuntime, LoopView
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import (
    EncoderFault,
    EncoderReader,
    EncoderReaderConfig,
    EncoderReading,
    LinearGratingCalibration,
)
from comp_daemon.rt.encoder_reader import FaultKind as EncoderFaultKind
from comp_daemon.rt.grating_cal import GratingCalibration
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply
from comp_daemon.rt.rsi_server import RsiServerConfig, RsiServerProtocol, RsiServerStats, start_rsi_server
from comp_daemon.rt.rt_thread import apply_scheduling, request_wakeup_latency
from comp_daemon.rt.safety import (
    Event,
    Fault,
    Faulted,
    FaultKind,
    Reaction,
    SafetySettings,
    SafetyState,
    arm,
    fault,
    release,
    reset,
    shutdown,
)

__all__ = [
    "LoopStart",
    "ReaderMirror",
    "RealtimeProcess",
    "RemoteRuntime",
    "RtProcessError",
    "RtStart",
    "StateReport",
    "main",
]

log = logging.getLogger(__name__)

V = TypeVar("V", bound=LoopView)

_ZERO = (0.0,) * 6
_RSI_COUNTERS = (
    "received",
    "answered",
    "garbled",
    "foreign",
    "superseded",
    "handler_errors",
    "late",
    "ipoc_skipped",
    "send_errors",
    "controller_delay",
)
_COMMANDS = frozenset({"arm", "release", "reset", "fault", "shutdown", "set_calibration"})
#: state reports are skipped (their contents accumulate) while this much is queued to a slow daemon
_BACKLOG_BYTES = 4 * 1024 * 1024


class RtProcessError(RuntimeError):
    """The real-time process failed, refused a request or has gone."""


# ---------------------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class RtStart:
    """The first request: where to run, and the RSI endpoint to open."""

    rsi: RsiServerConfig
    cpu: int | None = None
    priority: int = 0
    cpu_wakeup_latency_us: int | None = None
    push_period_s: float = 0.025
    tick_s: float = 0.05
    grace_cycles: int = 3  # replies with Stop = 1 before the child closes the endpoint on its own
    log_level: int = logging.INFO


@dataclass(frozen=True, slots=True)
class LoopStart:
    """The second request: the grating readers and the loop (once the ports are known)."""

    readers: tuple[tuple[EncoderReaderConfig, LinearGratingCalibration], ...]
    calibration: GratingCalibration | None
    safety: SafetySettings
    loop: JointLoopSettings
    sen_type: str = "ImFree"
    rsi_alive_s: float = 0.5

    def build(self, cls: type[V], sources: Mapping[int, FeedbackSource], clock_ns: Callable[[], int]) -> V:
        """The loop (``LoopRuntime``, in the child) or its view (``RemoteRuntime``, in the daemon)."""
        return cls(
            sources,
            calibration=self.calibration,
            safety=self.safety,
            loop=self.loop,
            sen_type=self.sen_type,
            clock_ns=clock_ns,
            rsi_alive_s=self.rsi_alive_s,
        )


@dataclass(frozen=True, slots=True)
class StateReport:
    """The child's state as of ``now_ns``; the sample and fault fields hold what is new since the last."""

    applied: int  # sequence number of the last command applied
    now_ns: int
    core: Any  # LoopCore
    telegrams: int
    last_ipoc: int | None
    last_actual_deg: tuple[float, ...] | None
    last_setpoint_deg: tuple[float, ...] | None
    last_angles_deg: tuple[float | None, ...]
    last_stop: bool
    last_ak_deg: tuple[float, ...]
    replies_after_shutdown: int
    last_rx_ns: int | None
    readings: tuple[EncoderReading | EncoderFault, ...]
    reader_counts: tuple[tuple[int, dict[EncoderFaultKind, int], int], ...]  # joint, faults, warnings
    rsi_counters: tuple[int | None, ...]  # in the order of _RSI_COUNTERS
    latency_ns: bytes  # new samples, array('q')
    jitter_ns: bytes
    trace: tuple[Any, ...]  # new rows of LoopRuntime.trace
    faults: tuple[Fault, ...]  # new entries of LoopRuntime.fault_log
    calibration_version: int | None


# ---------------------------------------------------------------------------------------- the child


class _LinkLogHandler(logging.Handler):
    """Sends the child's log records to the daemon, which logs them under the same logger names."""

    def __init__(self, link: LinkProtocol) -> None:
        super().__init__()
        self.link = link
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            if not self.link.send(("log", record.name, record.levelno, text)):
                sys.stderr.write(f"comp-daemon rt: {logging.getLevelName(record.levelno)} {text}\n")
        except Exception:
            self.handleError(record)


class RtChild:
    """The child's side: serves the daemon's requests, reports, goes safe when the daemon has gone."""

    def __init__(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.link = LinkProtocol(self._on_message, self._on_link_lost)
        self.start_cfg: RtStart | None = None
        self.runtime: LoopRuntime | None = None
        self.rsi: RsiServerProtocol | None = None
        self.rsi_transport: asyncio.DatagramTransport | None = None
        self.readers: dict[int, EncoderReader] = {}
        self.reader_tasks: list[asyncio.Task[None]] = []
        self.tasks: list[asyncio.Task[Any]] = []
        self.applied = 0
        self.done = asyncio.Event()
        self.exit_code = 0
        self.going_safe = False
        self._pm_qos: BinaryIO | None = None
        self._push_period_ns = 25_000_000
        self._last_push_ns = 0
        self._push_scheduled = False
        self._marks = {"latency": 0, "jitter": 0, "telegrams": 0, "faults": 0}
        self._sen_type = "ImFree"

    # ---------------------------------------------------------------------------- the RSI handler

    def handle(self, telegram: RobTelegram) -> SenReply:
        runtime = self.runtime
        if runtime is None:  # telegrams before the loop is assembled: no correction
            return SenReply(telegram.ipoc, _ZERO, False, self._sen_type)
        reply = runtime.handle(telegram)
        rx_ns = runtime._last_rx_ns  # this telegram's time, taken by handle()
        if (
            not self._push_scheduled
            and rx_ns is not None
            and rx_ns - self._last_push_ns >= self._push_period_ns
        ):
            self._push_scheduled = True
            self.loop.call_soon(self.push)  # runs after the receive callback has sent the reply
        return reply

    # ---------------------------------------------------------------------------- reports

    def push(self) -> None:
        self._push_scheduled = False
        runtime, rsi = self.runtime, self.rsi
        if runtime is None or rsi is None or not self.link.connected:
            return
        if self.link.buffered_bytes() > _BACKLOG_BYTES:
            return
        now = runtime.clock_ns()
        self._last_push_ns = now
        stats = rsi.stats
        marks = self._marks
        new_rows = min(runtime.telegrams - marks["telegrams"], len(runtime.trace))
        trace = tuple(itertools.islice(runtime.trace, len(runtime.trace) - new_rows, None))
        new_faults = min(runtime.faults_logged - marks["faults"], len(runtime.fault_log))
        faults = tuple(itertools.islice(runtime.fault_log, len(runtime.fault_log) - new_faults, None))
        report = StateReport(
            applied=self.applied,
            now_ns=now,
            core=runtime.core,
            telegrams=runtime.telegrams,
            last_ipoc=runtime.last_ipoc,
            last_actual_deg=runtime.last_actual_deg,
            last_setpoint_deg=runtime.last_setpoint_deg,
            last_angles_deg=runtime.last_angles_deg,
            last_stop=runtime.last_stop,
            last_ak_deg=runtime.last_ak_deg,
            replies_after_shutdown=runtime.replies_after_shutdown,
            last_rx_ns=runtime._last_rx_ns,
            readings=tuple(r for _, r in runtime.encoder_status(now)),
            reader_counts=tuple(
                (j, dict(reader.fault_counts), reader.warnings) for j, reader in self.readers.items()
            ),
            rsi_counters=tuple(getattr(stats, name) for name in _RSI_COUNTERS),
            latency_ns=stats.latency.since(marks["latency"]).tobytes(),
            jitter_ns=stats.jitter.since(marks["jitter"]).tobytes(),
            trace=trace,
            faults=faults,
            calibration_version=None if runtime.calibration is None else runtime.calibration.version,
        )
        if self.link.send(("state", report)):
            marks["latency"], marks["jitter"] = stats.latency.count, stats.jitter.count
            marks["telegrams"], marks["faults"] = runtime.telegrams, runtime.faults_logged

    def push_soon(self) -> None:
        if not self._push_scheduled:
            self._push_scheduled = True
            self.loop.call_soon(self.push)

    async def _report_idle(self) -> None:
        """Reports while no telegrams come (after replies they are sent by :meth:`handle`)."""
        while True:
            await asyncio.sleep(self._push_period_ns / 1e9)
            runtime = self.runtime
            if runtime is not None and runtime.clock_ns() - self._last_push_ns >= 2 * self._push_period_ns:
                self.push()

    async def _forward_events(self, runtime: LoopRuntime) -> None:
        while True:
            event = await runtime.next_event()
            self.link.send(("event", event))
            self.push_soon()

    async def _tick(self, runtime: LoopRuntime, tick_s: float) -> None:
        while True:
            await asyncio.sleep(tick_s)
            runtime.tick()

    # ---------------------------------------------------------------------------- messages

    def _on_message(self, message: Any) -> None:
        kind = message[0]
        if kind == "cmd":
            _, seq, name, args = message
            self._command(seq, name, args)
        elif kind == "req":
            _, req, name, args = message
            task = self.loop.create_task(self._request(req, name, args), name=f"rt-request-{name}")
            self.tasks.append(task)
            task.add_done_callback(self.tasks.remove)
        else:
            log.error("rt: unknown message %r from the daemon", kind)

    def _command(self, seq: int, name: str, args: tuple[Any, ...]) -> None:
        runtime = self.runtime
        try:
            if runtime is None:
                raise RtProcessError("the loop is not started")
            if name not in _COMMANDS:
                raise RtProcessError(f"unknown command {name!r}")
            getattr(runtime, name)(*args)
        except Exception as exc:
            reason = f"{type(exc).__name__}: {exc}"
            log.error("rt: command %s refused: %s", name, reason)
            if name == "arm" and runtime is not None:
                self._refuse_target(runtime, str(args[0]), reason)
        finally:
            self.applied = seq
            self.push_soon()

    def _refuse_target(self, runtime: LoopRuntime, target_id: str, reason: str) -> None:
        core = runtime.core
        f = core.fault
        if f is None:
            kind = FaultKind.SHUTDOWN if core.state is SafetyState.STOPPING else FaultKind.FEEDBACK_FAULT
            f = Fault(
                kind, Reaction.FREEZE, f"the loop refused the target: {reason}", runtime.now_s(), target_id
            )
        else:
            f = replace(f, detail=f"the loop refused the target: {reason}", target_id=target_id)
        self.link.send(("event", Faulted(target_id, f, core.errors_deg)))

    async def _request(self, req: int, name: str, args: tuple[Any, ...]) -> None:
        try:
            value = await self._serve(name, args)
        except Exception as exc:
            self.link.send(("reply", req, False, (type(exc).__name__, str(exc))))
        else:
            self.link.send(("reply", req, True, value))

    async def _serve(self, name: str, args: tuple[Any, ...]) -> Any:
        if name == "rsi":
            return await self._start_rsi(*args)
        if name == "loop":
            return await self._start_loop(*args)
        if name == "samples":
            if self.runtime is None:
                raise RtProcessError("the loop is not started")
            n, timeout_s = args
            samples: list[CycleSample] = await self.runtime.samples(n, timeout_s)
            return samples
        if name == "close_rsi":
            self.push()
            if self.rsi_transport is not None:
                self.rsi_transport.close()
            return None
        if name == "stop":
            await self._stop_readers()
            self.push()
            self.loop.call_soon(self.done.set)
            return None
        raise RtProcessError(f"unknown request {name!r}")

    async def _start_rsi(self, cfg: RtStart) -> dict[str, Any]:
        if self.start_cfg is not None:
            raise RtProcessError("the RSI endpoint is already open")
        self.start_cfg = cfg
        logging.getLogger().setLevel(cfg.log_level)
        pinned, scheduler, notes = apply_scheduling(cfg.cpu, cfg.priority, who="the real-time process")
        if cfg.cpu_wakeup_latency_us is not None:
            self._pm_qos, note = request_wakeup_latency(cfg.cpu_wakeup_latency_us)
            if note is not None:
                notes.append(note)
        self._push_period_ns = int(cfg.push_period_s * 1e9)
        self._sen_type = cfg.rsi.sen_type
        gc.collect()
        gc.freeze()  # the child's start-up objects: out of every later collector pass
        self.rsi_transport, self.rsi = await start_rsi_server(self.handle, cfg.rsi)
        host, port = self.rsi_transport.get_extra_info("sockname")[:2]
        self.tasks.append(self.loop.create_task(self._report_idle(), name="rt-report"))
        return {
            "pid": os.getpid(),
            "rsi_address": (str(host), int(port)),
            "cpu": pinned,
            "scheduler": scheduler,
            "cpu_wakeup_latency_us": None if self._pm_qos is None else cfg.cpu_wakeup_latency_us,
            "notes": notes,
        }

    async def _start_loop(self, spec: LoopStart) -> tuple[int, ...]:
        if self.runtime is not None:
            raise RtProcessError("the loop is already started")
        assert self.start_cfg is not None, "the RSI endpoint comes first"
        readers = {
            rcfg.joint: EncoderReader(rcfg, geometry, clock=time.perf_counter_ns)
            for rcfg, geometry in spec.readers
        }
        runtime = spec.build(LoopRuntime, readers, time.perf_counter_ns)
        self.readers = readers
        for reader in readers.values():
            reader.next_telegram_ns = runtime.next_telegram_ns
            self.reader_tasks.append(reader.start())
        self.runtime = runtime
        self.tasks.append(self.loop.create_task(self._forward_events(runtime), name="rt-events"))
        self.tasks.append(self.loop.create_task(self._tick(runtime, self.start_cfg.tick_s), name="rt-tick"))
        gc.freeze()
        return runtime.joints

    # ---------------------------------------------------------------------------- going safe

    def _on_link_lost(self, exc: Exception | None) -> None:
        if self.done.is_set() or self.going_safe:
            return
        sys.stderr.write(f"comp-daemon rt: the daemon has gone ({exc or 'link closed'}); going safe\n")
        self.exit_code = 1
        self.loop.create_task(self.go_safe("the daemon has gone"))

    async def go_safe(self, reason: str) -> None:
        """Zero steps and ``Stop = 1`` for the grace cycles, then close the endpoint and stop."""
        if self.going_safe:
            return
        self.going_safe = True
        runtime, cfg = self.runtime, self.start_cfg
        if runtime is not None and cfg is not None:
            runtime.shutdown()
            if runtime.rsi_alive():
                await runtime.wait_telegrams(cfg.grace_cycles, cfg.rsi.cycle_ms / 1000.0)
        if self.rsi_transport is not None:
            self.rsi_transport.close()
        await self._stop_readers()
        self.push()
        self.done.set()

    async def _stop_readers(self) -> None:
        for reader in self.readers.values():
            with contextlib.suppress(Exception):
                await reader.stop()

    async def close(self) -> None:
        for task in list(self.tasks):
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        if self.rsi_transport is not None:
            self.rsi_transport.close()
        await self._stop_readers()
        if self._pm_qos is not None:
            self._pm_qos.close()
        self.link.close()


async def _child_main(sock: socket.socket) -> int:
    loop = asyncio.get_running_loop()
    child = RtChild()
    await loop.create_unix_connection(lambda: child.link, sock=sock)
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(_LinkLogHandler(child.link))
    with contextlib.suppress(NotImplementedError, RuntimeError):
        loop.add_signal_handler(signal.SIGTERM, lambda: loop.create_task(child.go_safe("SIGTERM")))
    try:
        await child.done.wait()
        await asyncio.sleep(0)  # let the last reply and report reach the transport
        if child.link.transport is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(_drained(child.link), 2.0)
    finally:
        await child.close()
    return child.exit_code


async def _drained(link: LinkProtocol) -> None:
    while link.buffered_bytes() > 0:
        await asyncio.sleep(0.005)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="comp_daemon.daemon.rt_process", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--fd", type=int, required=True, help="this end of the daemon's socket pair")
    args = parser.parse_args(argv)
    try:
        sock = socket.socket(fileno=args.fd)
        if sock.family != socket.AF_UNIX or sock.type != socket.SOCK_STREAM:
            sock.detach()
            raise OSError("not a Unix stream socket")
    except OSError as exc:
        parser.error(f"--fd {args.fd}: not the daemon's socket pair ({exc}); the daemon starts this process")
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the daemon, which orders the stop
    logging.basicConfig(
        level=logging.INFO, stream=sys.stderr, format="comp-daemon rt: %(levelname)s %(message)s"
    )
    return asyncio.run(_child_main(sock))


# ---------------------------------------------------------------------------------------- the daemon's side


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
            log.warning("rt: %s not sent: the real-time process has gone", name)

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

    def tick(self) -> None:
        """Nothing to do: the child runs the loop's timers itself."""

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
                "comp_daemon.daemon.rt_process",
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
        self.readers = {
            rcfg.joint: ReaderMirror(rcfg.joint, rcfg.stale_after_ms, self.clock_ns)
            for rcfg, _ in spec.readers
        }
        runtime = spec.build(RemoteRuntime, self.readers, self.clock_ns)
        runtime.process = self
        self.runtime = runtime
        await self.request("loop", spec, timeout_s=30.0)
        return runtime

    async def close_rsi(self) -> None:
        await self.request("close_rsi", timeout_s=5.0)

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
            logging.getLogger(name).log(level, "%s", text)
        elif kind == "reply":
            _, req, ok, value = message
            fut = self._pending.get(req)
            if fut is not None and not fut.done():
                fut.set_result((ok, value))
        else:
            log.error("rt: unknown message %r from the real-time process", kind)

    def _on_report(self, report: StateReport) -> None:
        self.last_report_ns = report.now_ns
        stats = self.rsi_stats
        for name, value in zip(_RSI_COUNTERS, report.rsi_counters, strict=True):
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
            log.error("rt: the real-time process has gone (%s)", self.lost_reason)
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


if __name__ == "__main__":
    # run the package's copy of this module, not this ``__main__`` one: the messages must pickle
    # under their importable names (comp_daemon.daemon.rt_process.StateReport, …)
    from comp_daemon.daemon import rt_process

    sys.exit(rt_process.main())
