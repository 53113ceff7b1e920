"""The real-time process: the RSI endpoint, the grating readers and the loop in their own interpreter.

On one interpreter the RSI reply would share the GIL with the HTTP side: any C call that holds it (a
request body validated, a page of rows decoded, a collector pass) would delay the reply by its
length. So the whole real-time path runs in this child process of the daemon: the UDP endpoint
answering in its receive callback (:mod:`comp_daemon.rt.rsi_server`) and the
:class:`~comp_daemon.rt.loop.LoopRuntime` on one event loop, one reader task per grating
(:mod:`comp_daemon.rt.encoder_reader`) on a second event loop in a thread of its own (a tty poll can
wait in the kernel for a normal-priority worker: :mod:`comp_daemon.rt.reader_thread`), while the
daemon keeps the service, the executor and the store.

The daemon starts it as ``python -m comp_daemon.rt.child --fd N`` (N: its end of a socket pair;
the daemon's side is :mod:`comp_daemon.daemon.rt_process`). The child:

- pins itself to ``[realtime] cpu`` and takes ``SCHED_FIFO`` at ``[realtime] priority`` where
  permitted, holds the PM QoS request (:mod:`comp_daemon.rt.scheduling`), freezes its start-up
  objects out of the collector's sight;
- runs the loop's timers itself (``tick``), so a stalled daemon cannot keep a move timeout or a lost
  RSI connection from faulting the loop;
- reports to the daemon over the socket pair (:mod:`comp_daemon.rt.link`): a state report (core
  state, last cycle, grating readings, RSI counters and the latency of every reply since the last
  report) after a reply every ``push_period_s``; every safety event at once, right behind a state
  report (the daemon's mirror shows the state the event came from when the daemon reads the
  event); and its log records;
- goes safe on its own when the daemon has gone (the socket closes, whatever killed the daemon) or
  on SIGTERM: zero steps and ``Stop = 1`` for the grace cycles, then it closes the endpoint and
  exits. SIGINT is left to the daemon, which orders the shutdown.

Should the loop refuse a command the daemon's mirror accepted (a fault latched in between), an
``arm`` comes back as ``Faulted`` for that target, so the executor fails it with the reason.
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
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, BinaryIO

import structlog

from comp_daemon.common.logs import get_logger, plain_line
from comp_daemon.rt import cycle_trace
from comp_daemon.rt.encoder_reader import EncoderReader
from comp_daemon.rt.link import (
    COMMANDS,
    RSI_COUNTERS,
    LinkProtocol,
    LoopStart,
    RtProcessError,
    RtStart,
    StateReport,
)
from comp_daemon.rt.loop import CycleSample, LoopRuntime
from comp_daemon.rt.reader_thread import ReaderThread
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply
from comp_daemon.rt.rsi_server import RsiServerProtocol, start_rsi_server
from comp_daemon.rt.safety import Event, Fault, Faulted, FaultKind, Reaction, SafetyState
from comp_daemon.rt.scheduling import apply_scheduling, request_wakeup_latency

__all__ = ["RtChild", "main"]

log = get_logger(__name__)

_ZERO = (0.0,) * 6
#: state reports are skipped (their contents accumulate) while this much is queued to a slow daemon
_BACKLOG_BYTES = 4 * 1024 * 1024


def _configure_logging(link: LinkProtocol, level: int) -> None:
    """Every record (structlog or standard library) of this process goes to the daemon as text."""
    structlog.configure(
        processors=[
            structlog.stdlib.filter_by_level,
            structlog.contextvars.merge_contextvars,
            structlog.stdlib.PositionalArgumentsFormatter(),
            structlog.processors.format_exc_info,
            plain_line,
        ],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=False,
    )
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(_LinkLogHandler(link))
    root.setLevel(level)


class _LinkLogHandler(logging.Handler):
    """Sends the child's log records to the daemon, which logs them under the same logger names."""

    def __init__(self, link: LinkProtocol) -> None:
        super().__init__()
        self.link = link
        self.loop = asyncio.get_running_loop()
        self.loop_thread = threading.get_ident()
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
            if threading.get_ident() == self.loop_thread:
                self._send(record.name, record.levelno, text)
            else:  # the grating readers' thread: the link is written from its own loop only
                self.loop.call_soon_threadsafe(self._send, record.name, record.levelno, text)
        except Exception:
            self.handleError(record)

    def _send(self, name: str, level: int, text: str) -> None:
        if not self.link.send(("log", name, level, text)):
            sys.stderr.write(f"comp-daemon rt: {logging.getLevelName(level)} {text}\n")


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
        self.reader_thread: ReaderThread | None = None
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
        self.trace: cycle_trace.CycleTrace | None = None

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

    def _new_session(self, number: int, sender: tuple[str, int], what: str) -> None:
        if number > 1 and self.runtime is not None:
            self.runtime.new_session(what)

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
            rsi_counters=tuple(getattr(stats, name) for name in RSI_COUNTERS),
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
        """Reports while no telegrams come (after replies they are sent by :meth:`handle`), at the
        same period: the daemon's copy of the grating readings must not age more while RSI is off."""
        while True:
            await asyncio.sleep(self._push_period_ns / 2e9)
            runtime = self.runtime
            if runtime is None:
                continue
            now, period = runtime.clock_ns(), self._push_period_ns
            rx = runtime._last_rx_ns
            if now - self._last_push_ns >= period and (rx is None or now - rx >= period):
                self.push()

    async def _forward_events(self, runtime: LoopRuntime) -> None:
        while True:
            event = await runtime.next_event()
            self.send_event(event)

    def send_event(self, event: Event) -> None:
        """A state report, then the event: the daemon acts on an event (the executor finishes the
        target, claims the next one after the readiness check) as soon as it reads it, so its mirror
        must already show the state the event came from (the fault latched, the grating gone). Sent
        the other way round, a report delayed behind the event (this process not scheduled between
        the two) let the daemon decide on the state before the event."""
        self.push()
        self.link.send(("event", event))

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
            log.error(f"rt: unknown message {kind!r} from the daemon")

    def _command(self, seq: int, name: str, args: tuple[Any, ...]) -> None:
        runtime = self.runtime
        refused: Faulted | None = None
        try:
            if runtime is None:
                raise RtProcessError("the loop is not started")
            if name not in COMMANDS:
                raise RtProcessError(f"unknown command {name!r}")
            getattr(runtime, name)(*args)
        except Exception as exc:
            reason = f"{type(exc).__name__}: {exc}"
            log.error(f"rt: command {name} refused: {reason}")
            if name == "arm" and runtime is not None:
                refused = self._refused_target(runtime, str(args[0]), reason)
        finally:
            self.applied = seq
            if refused is not None:
                self.send_event(refused)  # the report (this command applied) goes first
            else:
                self.push_soon()

    def _refused_target(self, runtime: LoopRuntime, target_id: str, reason: str) -> Faulted:
        core = runtime.core
        f = core.fault
        if f is None:
            kind = FaultKind.SHUTDOWN if core.state is SafetyState.STOPPING else FaultKind.FEEDBACK_FAULT
            f = Fault(
                kind, Reaction.FREEZE, f"the loop refused the target: {reason}", runtime.now_s(), target_id
            )
        else:
            f = replace(f, detail=f"the loop refused the target: {reason}", target_id=target_id)
        return Faulted(target_id, f, core.errors_deg)

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
            (grace_cycles,) = args
            runtime, cfg = self.runtime, self.start_cfg
            if runtime is not None and cfg is not None:
                await runtime.wait_stop_replies(grace_cycles, cfg.rsi.cycle_ms / 1000.0)
            self.push()  # before the reply: the daemon reads the final state from it
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
        logging.getLogger().setLevel(cfg.log_level)  # the daemon's level, now that it is known
        pinned, scheduler, notes = apply_scheduling(cfg.cpu, cfg.priority, who="the real-time process")
        if cfg.cpu_wakeup_latency_us is not None:
            self._pm_qos, note = request_wakeup_latency(cfg.cpu_wakeup_latency_us)
            if note is not None:
                notes.append(note)
        self._push_period_ns = int(cfg.push_period_s * 1e9)
        self._sen_type = cfg.rsi.sen_type
        try:
            self.trace = cycle_trace.from_environment()
        except ValueError as exc:
            raise RtProcessError(str(exc)) from None
        gc.collect()
        gc.freeze()  # the child's start-up objects: out of every later collector pass
        self.rsi_transport, self.rsi = await start_rsi_server(
            self.handle, cfg.rsi, on_new_session=self._new_session, trace=self.trace
        )
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
        # the readers poll their ttys on a thread of their own (comp_daemon.rt.reader_thread): a
        # tty poll can wait in the kernel for a normal-priority worker, and must not hold a reply
        self.reader_thread = ReaderThread()
        for reader in readers.values():
            reader.next_telegram_ns = runtime.next_telegram_ns
            await self.reader_thread.start(reader)
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
            await runtime.wait_stop_replies(cfg.grace_cycles, cfg.rsi.cycle_ms / 1000.0)
        if self.rsi_transport is not None:
            self.rsi_transport.close()
        await self._stop_readers()
        self.push()
        self.done.set()

    async def _stop_readers(self) -> None:
        thread = self.reader_thread
        if thread is None:
            return
        for reader in self.readers.values():
            with contextlib.suppress(Exception):
                await thread.stop(reader)

    async def close(self) -> None:
        for task in list(self.tasks):
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        if self.rsi_transport is not None:
            self.rsi_transport.close()
        await self._stop_readers()
        if self.reader_thread is not None:
            self.reader_thread.close()
        if self._pm_qos is not None:
            self._pm_qos.close()
        if self.trace is not None:
            self.trace.close()
            try:
                self.trace.write()
            except OSError as exc:
                sys.stderr.write(
                    f"comp-daemon rt: could not write the cycle trace to {self.trace.path}: {exc}\n"
                )
        self.link.close()


async def _child_main(sock: socket.socket) -> int:
    loop = asyncio.get_running_loop()
    child = RtChild()
    await loop.create_unix_connection(lambda: child.link, sock=sock)
    _configure_logging(child.link, logging.INFO)
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
    parser = argparse.ArgumentParser(prog="comp_daemon.rt.child", description=__doc__.splitlines()[0])
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
    # until the link is up: plain lines on stderr, which the daemon's journal keeps
    logging.basicConfig(
        level=logging.INFO, stream=sys.stderr, format="comp-daemon rt: %(levelname)s %(message)s"
    )
    return asyncio.run(_child_main(sock))


if __name__ == "__main__":
    # run the package's copy of this module, not this ``__main__`` one (one set of module globals)
    from comp_daemon.rt import child

    sys.exit(child.main())
