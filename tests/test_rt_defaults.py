"""A configuration without ``[realtime]``: the daemon asks for what config.example.toml recommends
(SCHED_FIFO 20 on the last CPU, a 0 µs CPU wake-up latency request), falls back cleanly where the
system refuses, and says in one start-up line what it got.

Real ``comp-daemon run --sim`` processes; the refusal is made real by starting the daemon without
``CAP_SYS_NICE`` (dropped from its capability bounding set before exec, as a unit without
``AmbientCapabilities``/``LimitRTPRIO`` would run it).
"""

from __future__ import annotations

import ctypes
import json
import os
import resource
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from e2e_daemon import DaemonProcess, wait_until

from comp_daemon.service.config import RealtimeSettings

_PR_CAPBSET_DROP = 24
_CAP_SYS_NICE = 23
_LINE = "daemon: real-time loop:"


def _without_sys_nice() -> None:
    """In the daemon's process before exec: no CAP_SYS_NICE, no real-time priority allowed."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_CAPBSET_DROP, _CAP_SYS_NICE, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP, CAP_SYS_NICE)")
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path)  # its configuration has no [realtime] section
    assert "[realtime]" not in d.config_path.read_text()
    yield d
    d.cleanup()


def start_and_read(d: DaemonProcess, preexec_fn: Callable[[], None] | None = None) -> tuple[str, str]:
    """Start the daemon; its one start-up line about the real-time loop, and /api/status's word."""
    d.start(preexec_fn=preexec_fn)
    d.wait_http(90)
    records = [json.loads(line) for line in d.log_text().splitlines() if line.startswith("{")]
    lines = [r for r in records if str(r.get("event", "")).startswith(_LINE)]
    assert len(lines) == 1, d.tail()
    with d.client() as c:

        def word() -> str | None:
            value: str | None = c.get("/api/status").json()["daemon"]["loop"]["realtime"]
            return value

        said = wait_until(word, 30, "loop.realtime in /api/status")
    return f"{lines[0]['level']}: {lines[0]['event']}", said


def test_the_defaults_are_the_recommended_ones() -> None:
    rt = RealtimeSettings()
    assert (rt.cpu, rt.priority, rt.cpu_wakeup_latency_us, rt.keep_jobs_off_cpu) == ("auto", 20, 0, True)


def test_without_a_realtime_section_the_loop_asks_for_fifo_and_the_wakeup_latency(
    daemon: DaemonProcess,
) -> None:
    """Granted or refused, the line names both requests (before, neither was made: normal
    scheduling and sleeping CPUs, with nothing said)."""
    line, word = start_and_read(daemon)
    assert "SCHED_FIFO 20 scheduling" in line or "could not set SCHED_FIFO priority 20" in line, line
    assert (
        "CPU wake-up latency ≤ 0 µs requested" in line
        or "could not request a CPU wake-up latency of 0 µs" in line
    ), line
    assert word in line
    if os.geteuid() == 0 and os.access("/dev/cpu_dma_latency", os.W_OK):
        assert "SCHED_FIFO 20 scheduling" in line and "CPU wake-up latency ≤ 0 µs requested" in line, line
    assert line.startswith("info: ") or "could not" in line, line
    assert "rt: could not" not in daemon.log_text()  # no second line about the same thing


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping a capability from the bounding set needs root")
def test_refused_priority_falls_back_to_normal_scheduling_and_says_so(daemon: DaemonProcess) -> None:
    line, word = start_and_read(daemon, _without_sys_nice)
    assert "normal scheduling" in line and "could not set SCHED_FIFO priority 20" in line, line
    assert "grant CAP_SYS_NICE or LimitRTPRIO" in line and word in line
    assert line.startswith("warning: "), line
    with daemon.client() as c:  # and the loop answers the controller at normal priority

        def answering() -> bool:
            loop = c.get("/api/status").json()["daemon"]["loop"]
            return bool(loop["running"]) and int(loop["cycles"]) > 100

        wait_until(answering, 60, "the loop answering telegrams")
