"""Where and how the real-time process runs: its CPU, its scheduling class, the CPU wake-up latency.

The real-time process (:mod:`comp_daemon.rt.child`) applies these to itself at start-up; the daemon
uses :func:`resolve_cpu` and :func:`other_cpus` to choose that CPU and keep the job pool's workers
off it. All optional, all Linux:

- ``cpu``: the process is pinned to this CPU (``sched_setaffinity``); ``"auto"`` is the
  highest-numbered CPU when there are two or more (:func:`resolve_cpu`).
- ``priority`` > 0: ``SCHED_FIFO`` at that priority, so a telegram's wake-up pre-empts the fit
  workers and the HTTP side at once. Needs ``CAP_SYS_NICE`` or ``LimitRTPRIO`` (the systemd unit
  grants it); refused → logged, and the process runs at normal priority.
- ``cpu_wakeup_latency_us`` ≥ 0: a PM QoS request on ``/dev/cpu_dma_latency``, held while the
  process runs — the CPUs stay out of idle states slower to leave than this (0: polling idle, as
  ``cyclictest`` and tuned's real-time profiles ask). It keeps a sleeping CPU from adding its wake-up
  time to a reply, at the cost of power. Needs root or write access to the device; refused → logged.

Each refusal is returned as a note for the operator, not logged here: the daemon says in one
start-up line what was granted and what was refused, and shows the same in ``loop.realtime``.
"""

from __future__ import annotations

import os
import struct
from typing import BinaryIO

__all__ = [
    "PM_QOS_DEVICE",
    "apply_scheduling",
    "check_cpus",
    "other_cpus",
    "request_wakeup_latency",
    "resolve_cpu",
]

PM_QOS_DEVICE = "/dev/cpu_dma_latency"


def resolve_cpu(setting: int | str) -> int | None:
    """The CPU for the real-time process: a number as given, ``"none"`` → None, ``"auto"`` → the
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

    Returns (the CPU pinned to or None, the scheduling in words, what could not be applied); the
    caller reports the refusals and keeps running with what it has.
    """
    pinned: int | None = None
    scheduler = "normal"
    notes: list[str] = []
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})  # 0: the calling thread; threads it starts inherit it
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
    return pinned, scheduler, notes


def request_wakeup_latency(us: int, device: str = PM_QOS_DEVICE) -> tuple[BinaryIO | None, str | None]:
    """Open a PM QoS request for CPU wake-up latency ≤ ``us`` µs; it holds while the file stays open.

    Returns (the open file, None) or (None, why it was refused).
    """
    fh = None
    try:
        fh = open(device, "wb", buffering=0)  # held open for the request's lifetime
        fh.write(struct.pack("i", us))
    except OSError as exc:
        if fh is not None:
            fh.close()
        return None, f"could not request a CPU wake-up latency of {us} µs ({exc})"
    return fh, None
