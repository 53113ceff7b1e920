"""The real-time thread: its own event loop, CPU and scheduling, and the loop runtime shared across threads.

The daemon runs the RSI endpoint and the grating readers on a second event loop in a thread of its
own; the executor and the operator's commands stay on the service loop. What is checked here: the
thread starts, runs coroutines and calls, reports what it could not apply and stops; and
:class:`LoopRuntime` keeps every command and delivers every event when its handler runs on that
thread while commands arrive from the service loop.
"""

from __future__ import annotations

import asyncio
import os
import struct
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_daemon_executor import HOME, JOINTS, Clock, Grating, Robot, calibration

from comp_daemon.daemon.runtime import LoopRuntime
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.rt_thread import RealtimeThread, RealtimeThreadConfig, other_cpus, resolve_cpu
from comp_daemon.rt.safety import Arrived, SafetySettings, SafetyState, SafetyTransitionError


@pytest.fixture
def rt() -> Iterator[RealtimeThread]:
    before = sys.getswitchinterval()
    thread = RealtimeThread(RealtimeThreadConfig(name="test-rt", switch_interval_s=0.0002, heartbeat_s=0.01))
    thread.start()
    yield thread
    thread.stop()
    assert sys.getswitchinterval() == before  # the process's own setting is back


async def test_runs_coroutines_and_calls_on_its_own_thread(rt: RealtimeThread) -> None:
    async def where() -> tuple[int, asyncio.AbstractEventLoop]:
        await asyncio.sleep(0)
        return threading.get_ident(), asyncio.get_running_loop()

    ident, loop = await rt.run(where())
    assert ident != threading.get_ident() and loop is rt.loop
    assert await rt.call(threading.get_ident) == ident
    with pytest.raises(ZeroDivisionError):
        await rt.call(lambda: 1 / 0)  # an exception comes back to the caller
    assert sys.getswitchinterval() == pytest.approx(0.0002)
    await asyncio.sleep(0.05)
    age = rt.heartbeat_age_s()
    assert age is not None and age < 0.5 and rt.alive


async def test_stop_cancels_its_tasks_and_refuses_more_work() -> None:
    thread = RealtimeThread(RealtimeThreadConfig(switch_interval_s=None))
    thread.start()
    cancelled = threading.Event()

    async def forever() -> None:
        try:
            await asyncio.sleep(3600)
        finally:
            cancelled.set()

    assert thread.loop is not None
    asyncio.run_coroutine_threadsafe(forever(), thread.loop)
    await asyncio.sleep(0.05)
    await asyncio.to_thread(thread.stop)
    assert cancelled.is_set() and not thread.alive
    with pytest.raises(RuntimeError, match="not running"):
        await thread.call(int)
    coro = asyncio.sleep(0)
    with pytest.raises(RuntimeError, match="not running"):
        await thread.run(coro)
    thread.stop()  # idempotent


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
def test_cpu_choice() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    assert resolve_cpu("none") is None and resolve_cpu(3) == 3
    assert resolve_cpu("auto") == (cpus[-1] if len(cpus) > 1 else None)
    assert other_cpus(None) is None
    if len(cpus) > 1:
        assert other_cpus(cpus[-1]) == set(cpus[:-1])
    with pytest.raises(ValueError, match="'fast'"):
        resolve_cpu("fast")


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
def test_pinning_applies_to_the_thread_only() -> None:
    cpu = sorted(os.sched_getaffinity(0))[0]
    before = os.sched_getaffinity(0)
    thread = RealtimeThread(RealtimeThreadConfig(cpu=cpu, switch_interval_s=None))
    thread.start()
    try:
        assert thread.loop is not None
        fut = asyncio.run_coroutine_threadsafe(_affinity(), thread.loop)
        assert fut.result(5) == {cpu}
        assert thread.pinned_cpu == cpu and thread.describe()["cpu"] == cpu
        assert os.sched_getaffinity(0) == before  # the calling thread keeps its CPUs
    finally:
        thread.stop()


async def _affinity() -> set[int]:
    return set(os.sched_getaffinity(0))


def test_refused_settings_are_reported_not_fatal(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "sched_setaffinity", refuse)
    thread = RealtimeThread(RealtimeThreadConfig(cpu=0, realtime_priority=20, switch_interval_s=None))
    thread.start()
    try:
        d = thread.describe()
        assert d["scheduler"] == "normal" and d["cpu"] is None
        assert any("SCHED_FIFO" in n and "CAP_SYS_NICE" in n for n in d["notes"]), d["notes"]
        assert any("pin" in n for n in d["notes"]), d["notes"]
        assert thread.alive
    finally:
        thread.stop()


# ------------------------------------------------------------------------------ runtime across threads


def _runtime(clock: Clock, robot: Robot) -> LoopRuntime:
    return LoopRuntime(
        {j: Grating(robot, j) for j in JOINTS},
        calibration=calibration(),
        safety=SafetySettings(),
        loop=JointLoopSettings(),
        clock_ns=clock,
    )


async def test_events_and_samples_reach_the_service_loop(rt: RealtimeThread) -> None:
    clock = Clock()
    robot = Robot(clock)
    runtime = _runtime(clock, robot)  # created on this (the service) loop: events are delivered here
    commanded = tuple(h + 0.01 for h in HOME)
    runtime.arm("7", commanded, tuple(commanded[j - 1] for j in JOINTS))
    robot.goal = list(commanded)

    def cycles(n: int) -> None:
        for _ in range(n):
            clock.ns += 12_000_000
            reply = runtime.handle(robot.telegram())
            robot.pending.append(reply.ak_deg)

    sampling = asyncio.ensure_future(runtime.samples(5, timeout_s=5.0))
    await asyncio.sleep(0)  # registered
    await rt.call(cycles, 10)
    event = await asyncio.wait_for(runtime.next_event(), 5.0)
    assert isinstance(event, Arrived) and event.target_id == "7"
    samples = await asyncio.wait_for(sampling, 5.0)
    assert len(samples) == 5 and all(s.counts[0] is not None for s in samples)


async def test_no_command_is_lost_to_a_concurrent_telegram(rt: RealtimeThread) -> None:
    """Commands from this loop while the handler runs flat out on the real-time thread."""
    clock = Clock()
    robot = Robot(clock)
    runtime = _runtime(clock, robot)
    stop = threading.Event()

    def hammer() -> int:
        n = 0
        while not stop.is_set():
            clock.ns += 12_000_000
            reply = runtime.handle(robot.telegram())
            robot.pending.append(reply.ak_deg)  # the robot applies the corrections: they converge
            n += 1
        return n

    handled = asyncio.ensure_future(rt.call(hammer))
    commanded = tuple(HOME)
    deadline = time.monotonic() + 1.0
    rounds = 0
    try:
        while time.monotonic() < deadline:
            runtime.arm(f"t{rounds}", commanded, tuple(commanded[j - 1] for j in JOINTS))
            # had a telegram's core replaced the armed one, the state would not show the target
            core = runtime.core
            assert core.target_id == f"t{rounds}" and core.state is not SafetyState.IDLE
            with pytest.raises(SafetyTransitionError):
                runtime.arm("again", commanded, tuple(commanded[j - 1] for j in JOINTS))
            runtime.release()
            assert runtime.core.target_id is None
            rounds += 1
            await asyncio.sleep(0)
    finally:
        stop.set()
        n = await handled
    assert rounds > 20 and n > 100


def test_runtime_forecasts_the_next_telegram() -> None:
    clock = Clock()
    robot = Robot(clock)
    runtime = _runtime(clock, robot)  # cycle 12 ms
    assert runtime.next_telegram_ns() is None  # none seen yet
    runtime.handle(robot.telegram())
    t0 = clock.ns
    assert runtime.next_telegram_ns() == t0 + 12_000_000
    clock.ns += 30_000_000  # two cycles missed: the one after
    assert runtime.next_telegram_ns() == t0 + 36_000_000
    clock.ns += 30_000_000  # five cycles without a telegram: RSI has stopped, no forecast
    assert runtime.next_telegram_ns() is None


def test_wakeup_latency_request_is_held_while_running(tmp_path: Path) -> None:
    """The PM QoS request is written as the kernel reads it (s32) and withdrawn (closed) on stop."""
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    thread = RealtimeThread(
        RealtimeThreadConfig(switch_interval_s=None, cpu_wakeup_latency_us=0, pm_qos_device=str(device))
    )
    thread.start()
    try:
        assert device.read_bytes() == struct.pack("i", 0)
        assert thread.describe()["cpu_wakeup_latency_us"] == 0 and thread._pm_qos is not None
    finally:
        thread.stop()
    assert thread._pm_qos is None
    refused = RealtimeThread(
        RealtimeThreadConfig(switch_interval_s=None, cpu_wakeup_latency_us=0, pm_qos_device="/nonexistent/x")
    )
    refused.start()
    try:
        assert refused.describe()["cpu_wakeup_latency_us"] is None
        assert any("wake-up latency" in n for n in refused.notes)
    finally:
        refused.stop()


async def test_replies_keep_coming_while_the_service_loop_is_blocked(rt: RealtimeThread) -> None:
    """The point of the thread: a stalled service loop (here 0.3 s inside a blocking call, as a
    slow disk or a stuck library would) does not stall the RSI replies. On one shared event loop
    this test fails (about 25 replies would wait up to 300 ms)."""
    import socket

    from comp_daemon.rt.rsi_codec import build_rob, parse_sen
    from comp_daemon.rt.rsi_server import RsiServerConfig, start_rsi_server

    clock = Clock()
    robot = Robot(clock)
    runtime = _runtime(clock, robot)
    config = RsiServerConfig(controller_host="127.0.0.1", bind_host="127.0.0.1", bind_port=0)
    transport, proto = await rt.run(start_rsi_server(runtime.handle, config))
    port = transport.get_extra_info("sockname")[1]
    latencies_ms: list[float] = []
    answered: list[int] = []

    def controller() -> None:  # the KR C4: a telegram every 12 ms, each reply awaited
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.1)
            for k in range(60):
                t0 = time.perf_counter()
                s.sendto(build_rob(1000 + 12 * k, HOME, HOME, delay=0), ("127.0.0.1", port))
                try:
                    answered.append(parse_sen(s.recv(4096)).ipoc)
                    latencies_ms.append((time.perf_counter() - t0) * 1e3)
                except TimeoutError:
                    pass
                time.sleep(max(0.0, 0.012 - (time.perf_counter() - t0)))

    sender = asyncio.ensure_future(asyncio.to_thread(controller))
    await asyncio.sleep(0.1)
    t_block = time.perf_counter()
    time.sleep(0.3)  # the service loop is stuck; the GIL is free
    blocked_s = time.perf_counter() - t_block
    await sender
    await rt.call(transport.close)
    assert blocked_s >= 0.3
    assert answered == [1000 + 12 * k for k in range(60)], "a reply was missing"
    # generous bounds (a shared CI machine), yet far below the 300 ms a shared loop would add
    assert max(latencies_ms) < 100.0, latencies_ms
    assert runtime.telegrams == 60 and proto.stats.answered == 60


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
@pytest.mark.parametrize(
    ("section", "fragment"),
    [
        ("[jobs]\ncpus = [0, 4099]\n", "jobs.cpus names CPU 4099"),
        ("[realtime]\ncpu = 4099\n", "realtime.cpu"),
    ],
)
def test_run_refuses_cpus_the_machine_lacks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], section: str, fragment: str
) -> None:
    from comp_daemon.cli import main

    data = tmp_path / "var"
    config = tmp_path / "config.toml"
    config.write_text(f'[store]\ndata_dir = "{data}"\n{section}', encoding="utf-8")
    assert main(["run", "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert fragment in err and "it may use" in err, err
    assert not data.exists()  # refused before anything was created
