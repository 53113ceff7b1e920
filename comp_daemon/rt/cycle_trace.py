"""A per-cycle trace of the real-time process: when each telegram came, what held up its reply.

Off by default. With ``COMP_DAEMON_RT_TRACE=PATH`` in the daemon's environment, the real-time
process (:mod:`comp_daemon.rt.child`) records one row per answered telegram into a ring of
``COMP_DAEMON_RT_TRACE_CYCLES`` rows (default 1 000 000, 14 × 8 bytes a row, allocated and touched
at start so that filling it costs no page fault) and writes it to ``PATH`` (NumPy ``.npz``, one
array per column) when it exits. ``benchmarks/bench_rsi_loop.py`` uses it to say, for each late
reply on the wire, what the process was doing. The columns:

- ``ipoc``: the telegram answered;
- ``kernel_first_ns`` / ``kernel_last_ns``: when the first and the last datagram taken in this
  receive callback reached the kernel (the socket's receive timestamp, ``SIOCGSTAMPNS``, taken
  when the packet is queued to the network stack, before the softirq delivers it to the socket;
  CLOCK_REALTIME);
- ``entry_ns`` / ``sent_ns``: receive callback entry and ``sendto`` returned (CLOCK_REALTIME);
- ``taken``: valid telegrams taken in this callback (more than one: the others were superseded);
- ``cpu_ns``: CPU time this thread used between the previous reply and this callback's entry
  (the interpreter busy elsewhere: other callbacks, the collector);
- ``run_delay_ns``: time this thread waited runnable for a CPU in the same interval
  (``/proc/thread-self/schedstat``; another task of the same or a higher priority on its CPU);
- ``involuntary`` / ``voluntary``: context switches in the same interval (``getrusage``);
- ``faults``: page faults (minor + major) in the same interval;
- ``gc_ns`` / ``gc_gen``: time in the cyclic collector in the same interval and the highest
  generation collected (-1: none).

What a stall before the callback was, from the row: ``cpu_ns`` close to the wait → the process was
busy (``gc_ns`` says how much of it was the collector); ``run_delay_ns`` close to it → it was
runnable and another task had its CPU; neither → it slept while the datagram had reached the
kernel but not the socket (the network softirq deferred to ``ksoftirqd``, a normal-priority thread)
or the whole machine was held (hypervisor steal).
"""

from __future__ import annotations

import contextlib
import fcntl
import gc
import os
import resource
import socket
import struct
import time
from array import array
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["COLUMNS", "CycleTrace", "from_environment"]

ENV_PATH = "COMP_DAEMON_RT_TRACE"
ENV_CYCLES = "COMP_DAEMON_RT_TRACE_CYCLES"
SIOCGSTAMPNS = 0x8907  # <asm-generic/sockios.h>: the receive time of the last datagram read

COLUMNS = (
    "ipoc",
    "kernel_first_ns",
    "kernel_last_ns",
    "entry_ns",
    "sent_ns",
    "taken",
    "cpu_ns",
    "run_delay_ns",
    "involuntary",
    "voluntary",
    "faults",
    "gc_ns",
    "gc_gen",
    "seq",
)
_W = len(COLUMNS)
_STAMP = bytes(16)


class CycleTrace:
    """The ring of per-cycle rows (see the module docstring); written only by the loop's thread."""

    def __init__(self, path: Path, capacity: int = 1_000_000) -> None:
        if capacity < 1:
            raise ValueError(f"{ENV_CYCLES} must be at least 1, not {capacity}")
        self.path = path
        self.capacity = capacity
        self.rows = array("q", bytes(8 * _W * capacity))  # copied from zeros: every page touched now
        self.count = 0
        self._fd: int | None = None
        self._schedstat: int | None = None
        self._cpu_mark = time.thread_time_ns()
        self._delay_mark = 0
        self._usage_mark = (0, 0, 0)
        self._gc_ns = 0
        self._gc_gen = -1
        self._gc_start = 0
        self._entry_cpu = 0

    # ---------------------------------------------------------------------------- set-up

    def attach(self, sock: socket.socket) -> None:
        """Start the receive timestamps on the endpoint's socket and the counters of this thread."""
        self._fd = sock.fileno()
        with contextlib.suppress(OSError):  # the first call turns the timestamps on (ENOENT)
            fcntl.ioctl(self._fd, SIOCGSTAMPNS, _STAMP)
        with contextlib.suppress(OSError):
            self._schedstat = os.open("/proc/thread-self/schedstat", os.O_RDONLY)
        gc.callbacks.append(self._on_gc)
        self._cpu_mark = time.thread_time_ns()
        self._delay_mark = self._run_delay()
        self._usage_mark = self._usage()

    def close(self) -> None:
        with contextlib.suppress(ValueError):
            gc.callbacks.remove(self._on_gc)
        if self._schedstat is not None:
            os.close(self._schedstat)
            self._schedstat = None

    # ---------------------------------------------------------------------------- per cycle

    def kernel_stamp(self) -> int:
        """The kernel's receive time (ns, CLOCK_REALTIME) of the last datagram read on the socket."""
        if self._fd is None:
            return 0
        try:
            sec, nsec = struct.unpack("qq", fcntl.ioctl(self._fd, SIOCGSTAMPNS, _STAMP))
        except OSError:
            return 0
        return sec * 1_000_000_000 + nsec

    def entry(self) -> int:
        """At callback entry: the wall time, and the thread's CPU time since the last reply."""
        self._entry_cpu = time.thread_time_ns()
        return time.time_ns()

    def record(self, ipoc: int, kernel_first: int, kernel_last: int, entry: int, taken: int) -> None:
        """One answered telegram, right after its ``sendto``."""
        sent = time.time_ns()
        delay, usage = self._run_delay(), self._usage()
        row = (
            ipoc,
            kernel_first,
            kernel_last,
            entry,
            sent,
            taken,
            self._entry_cpu - self._cpu_mark,
            delay - self._delay_mark,
            usage[0] - self._usage_mark[0],
            usage[1] - self._usage_mark[1],
            usage[2] - self._usage_mark[2],
            self._gc_ns,
            self._gc_gen,
            self.count,
        )
        i = (self.count % self.capacity) * _W
        self.rows[i : i + _W] = array("q", row)
        self.count += 1
        self._cpu_mark = time.thread_time_ns()
        self._delay_mark, self._usage_mark = delay, usage
        self._gc_ns, self._gc_gen = 0, -1

    def _run_delay(self) -> int:
        if self._schedstat is None:
            return 0
        try:
            return int(os.pread(self._schedstat, 64, 0).split()[1])
        except (OSError, IndexError, ValueError):
            return 0

    @staticmethod
    def _usage() -> tuple[int, int, int]:
        u = resource.getrusage(resource.RUSAGE_THREAD)
        return u.ru_nivcsw, u.ru_nvcsw, u.ru_minflt + u.ru_majflt

    def _on_gc(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._gc_start = time.perf_counter_ns()
        else:
            self._gc_ns += time.perf_counter_ns() - self._gc_start
            self._gc_gen = max(self._gc_gen, int(info.get("generation", 0)))

    # ---------------------------------------------------------------------------- out

    def table(self) -> dict[str, np.ndarray]:
        """The retained rows, oldest first, one array per column."""
        n = min(self.count, self.capacity)
        a = np.frombuffer(self.rows, dtype=np.int64).reshape(self.capacity, _W)
        if self.count > self.capacity:
            start = self.count % self.capacity
            a = np.concatenate([a[start:], a[:start]])
        else:
            a = a[:n]
        return {name: a[:, k].copy() for k, name in enumerate(COLUMNS)}

    def write(self) -> None:
        tmp = self.path.with_name(self.path.name + ".part.npz")
        columns: dict[str, Any] = self.table()
        np.savez(tmp, **columns)
        os.replace(tmp, self.path)


def from_environment(environ: dict[str, str] | None = None) -> CycleTrace | None:
    """The trace asked for by ``COMP_DAEMON_RT_TRACE`` (None when it is not set)."""
    env = os.environ if environ is None else environ
    path = env.get(ENV_PATH)
    if not path:
        return None
    text = env.get(ENV_CYCLES, "1000000")
    try:
        cycles = int(text)
    except ValueError:
        raise ValueError(f"{ENV_CYCLES} must be a whole number of cycles, not {text!r}") from None
    return CycleTrace(Path(path), cycles)
