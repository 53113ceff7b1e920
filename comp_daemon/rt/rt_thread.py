"""A dedicated OS thread running its own asyncio event loop: the home of the RSI endpoint and the gratings.

The daemon's main event loop serves HTTP, the store, the executor and the job pool's bookkeeping;
any of those can keep it busy for milliseconds. The RSI reply must not wait for them, and neither
may the grating readers that feed it. So the RSI UDP endpoint and the encoder readers run on a
second event loop in this thread, unchanged (the same protocol answering in its receive callback,
the same reader tasks), and the main loop talks to them only through thread-safe calls.

What isolation the thread gets (all optional, all Linux):

- ``cpu``: the thread is pinned to this CPU (``sched_setaffinity`` on the thread). The job pool's
  workers are kept off it (:func:`other_cpus`).
- ``realtime_priority`` > 0: ``SCHED_FIFO`` at that priority, so a telegram's wake-up pre-empts the
  fit workers and the HTTP side at once. Needs ``CAP_SYS_NICE`` or ``LimitRTPRIO`` (the systemd unit
  grants it); refused → logged, and the thread runs at normal priority.
- ``switch_interval_s``: Python's GIL switch interval for the process (``sys.setswitchinterval``).
  A thread that wakes while another holds the GIL waits up to this long for it (default 5 ms);
  only contended switches pay for a smaller value, and the contended ones are the RSI thread's.

- ``cpu_wakeup_latency_us`` ≥ 0: a PM QoS request on ``/dev/cpu_dma_latency``, held while the
  thread runs — the CPUs stay out of idle states slower to leave than this (0: polling idle, as
  ``cyclictest`` and tuned's real-time profiles ask). It keeps a sleeping CPU from adding its wake-up
  time to a reply, at the cost of power. Needs root or write access to the device; refused → logged.

The thread also keeps a heartbeat (its loop's last turn, ns of the injected clock) so the
supervisor can tell a stalled real-time loop from a quiet one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import struct
import sys
import threading
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any, BinaryIO, TypeVar

__all__ = [
    "PM_QOS_DEVICE",
    "RealtimeThread",
    "RealtimeThreadConfig",
    "apply_scheduling",
    "check_cpus",
    "other_cpus",
    "request_wakeup_latency",
    "resolve_cpu",
]

log = logging.getLogger(__name__)

T = TypeVar("T")

PM_QOS_DEVICE = "/dev/cpu_dma_latency"


@dataclass(frozen=True, slots=True)
class RealtimeThreadConfig:
    name: str = "comp-daemon-rt"
    cpu: int | None = None
    realtime_priority: int = 0  # 0: normal scheduling; 1..99: SCHED_FIFO priority
    switch_interval_s: float | None = 0.0002  # None: leave Python's default
    cpu_wakeup_latency_us: int | None = None  # None: no PM QoS request
    pm_qos_device: str = PM_QOS_DEVICE
    heartbeat_s: float = 0.05


def resolve_cpu(setting: int | str) -> int | None:
    """The CPU for the real-time thread: a number as given, ``"none"`` → None, ``"auto"`` → the
    highest-numbered CPU this process may use when it may use two or more (else None)."""
    if isinstance(setting, int):
        return setting
    if setting == "none" or not hasattr(os, "sched_getaffinity"):
        return None
    if setting != "auto":
        raise ValueError(f"the real-time CPU is a number, 'auto' or 'none', not {setting!r}")
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[-1] if len(cpus) >= 2 else None


def check_cpus(cpus: list[int], setting: str) -> None:
    """ValueError naming ``setting`` when it lists a CPU this process may not run on (a typo, or a
    configuration copied from a larger machine); nothing to check off Linux."""
    if not hasattr(os, "sched_getaffinity"):
        return
    allowed = sorted(os.sched_getaffinity(0))
    missing = sorted(set(cpus) - set(allowed))
    if missing:
        raise ValueError(
            f"{setting} names CPU {', '.join(map(str, missing))}, which this process may not use "
            f"(it may use {', '.join(map(str, allowed))})"
        )


def other_cpus(cpu: int | None) -> set[int] | None:
    """The CPUs this process may use except ``cpu`` (None when there is nothing to exclude)."""
    if cpu is None or not hasattr(os, "sched_getaffinity"):
        return None
    rest = set(os.sched_getaffinity(0)) - {cpu}
    return rest or None


def apply_scheduling(cpu: int | None, priority: int, *, who: str) -> tuple[int | None, str, list[str]]:
    """Pin the calling thread to ``cpu`` and give it ``SCHED_FIFO`` at ``priority`` (0: leave it).

    Returns (the CPU pinned to or None, the scheduling in words, what could not be applied); each
    refusal is logged and the thread keeps running with what it has.
    """
    pinned: int | None = None
    scheduler = "normal"
    notes: list[str] = []
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})  # 0: the calling thread on Linux
            pinned = cpu
        except (OSError, AttributeError) as exc:
            notes.append(f"could not pin {who} to CPU {cpu}: {exc}")
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            scheduler = f"SCHED_FIFO {priority}"
        except (OSError, AttributeError) as exc:
            notes.append(
                f"could not set SCHED_FIFO priority {priority} ({exc}); "
                "grant CAP_SYS_NICE or LimitRTPRIO, running at normal priority"
            )
    for note in notes:
        log.warning("rt: %s", note)
    return pinned, scheduler, notes


def request_wakeup_latency(us: int, device: str = PM_QOS_DEVICE) -> tuple[BinaryIO | None, str | None]:
    """Open a PM QoS request for CPU wake-up latency ≤ ``us`` µs; it holds while the file stays open.

    Returns (the open file, None) or (None, why it was refused — also logged).
    """
    fh = None
    try:
        fh = open(device, "wb", buffering=0)  # held open for the request's lifetime
        fh.write(struct.pack("i", us))
    except OSError as exc:
        if fh is not None:
            fh.close()
        note = f"could not request a CPU wake-up latency of {us} µs ({exc})"
        log.warning("rt: %s", note)
        return None, note
    return fh, None


class RealtimeThread:
    """Start, use and stop the real-time event loop thread. See the module docstring."""

    def __init__(self, config: RealtimeThreadConfig, *, clock_ns: Callable[[], int] = time.perf_counter_ns):
        self.config = config
        self.clock_ns = clock_ns
        self.loop: asyncio.AbstractEventLoop | None = None
        self.thread: threading.Thread | None = None
        self.native_id: int | None = None
        self.heartbeat_ns: int | None = None
        self.pinned_cpu: int | None = None
        self.scheduler = "normal"
        self.notes: list[str] = []  # what could not be applied, for the operator
        self._switch_interval_before: float | None = None
        self._pm_qos: Any = None  # the open PM QoS request (closing it withdraws the request)
        self._ready = threading.Event()
        self._stopped = threading.Event()
        self._startup_error: BaseException | None = None

    # ---------------------------------------------------------------------------------- life cycle

    def start(self, timeout_s: float = 5.0) -> None:
        """Start the thread and wait until its loop runs (RuntimeError if it does not)."""
        if self.thread is not None:
            raise RuntimeError("the real-time thread is already started")
        cfg = self.config
        if cfg.switch_interval_s is not None:
            self._switch_interval_before = sys.getswitchinterval()
            sys.setswitchinterval(cfg.switch_interval_s)
        if cfg.cpu_wakeup_latency_us is not None:
            self._request_wakeup_latency(cfg.cpu_wakeup_latency_us)
        self.thread = threading.Thread(target=self._main, name=cfg.name, daemon=True)
        self.thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError(f"the real-time thread did not start within {timeout_s:g} s")
        if self._startup_error is not None:
            raise RuntimeError(f"the real-time thread failed to start: {self._startup_error}")

    def _main(self) -> None:
        try:
            self.native_id = threading.get_native_id()
            self._apply_scheduling()
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            self.loop = loop
        except BaseException as exc:  # reported by start()
            self._startup_error = exc
            self._ready.set()
            return
        heartbeat = loop.create_task(self._heartbeat(), name="rt-heartbeat")
        loop.call_soon(self._ready.set)
        try:
            loop.run_forever()
        finally:
            heartbeat.cancel()
            with contextlib.suppress(Exception):
                pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
                for t in pending:
                    t.cancel()
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()
            self._stopped.set()

    def _apply_scheduling(self) -> None:
        cfg = self.config
        self.pinned_cpu, self.scheduler, notes = apply_scheduling(
            cfg.cpu, cfg.realtime_priority, who="the real-time thread"
        )
        self.notes.extend(notes)

    def _request_wakeup_latency(self, us: int) -> None:
        self._pm_qos, note = request_wakeup_latency(us, self.config.pm_qos_device)
        if note is not None:
            self.notes.append(note)

    async def _heartbeat(self) -> None:
        while True:
            self.heartbeat_ns = self.clock_ns()
            await asyncio.sleep(self.config.heartbeat_s)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the loop (its tasks are cancelled), join the thread, withdraw the PM QoS request and
        restore the switch interval. Idempotent."""
        loop, thread = self.loop, self.thread
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(loop.stop)
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                log.error("rt: the real-time thread did not stop within %g s", timeout_s)
        if self._pm_qos is not None:
            self._pm_qos.close()
            self._pm_qos = None
        if self._switch_interval_before is not None:
            sys.setswitchinterval(self._switch_interval_before)
            self._switch_interval_before = None

    # ---------------------------------------------------------------------------------- use

    @property
    def alive(self) -> bool:
        return self.thread is not None and self.thread.is_alive() and not self._stopped.is_set()

    def heartbeat_age_s(self) -> float | None:
        hb = self.heartbeat_ns
        return None if hb is None else (self.clock_ns() - hb) * 1e-9

    def _require_loop(self) -> asyncio.AbstractEventLoop:
        if self.loop is None or self.loop.is_closed() or not self.alive:
            raise RuntimeError("the real-time thread is not running")
        return self.loop

    async def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run a coroutine on the real-time loop and await its result from the calling loop."""
        try:
            loop = self._require_loop()
        except RuntimeError:
            coro.close()
            raise
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, loop))

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Call a plain function on the real-time loop (between its callbacks) and await its result."""

        async def invoke() -> T:
            return fn(*args)

        return await self.run(invoke())

    def describe(self) -> dict[str, Any]:
        return {
            "thread": self.config.name,
            "native_id": self.native_id,
            "cpu": self.pinned_cpu,
            "scheduler": self.scheduler,
            "switch_interval_s": sys.getswitchinterval(),
            "cpu_wakeup_latency_us": None if self._pm_qos is None else self.config.cpu_wakeup_latency_us,
            "notes": list(self.notes),
        }
