"""The real-time process: the RSI endpoint and the loop in a child process, driven over real UDP.

What is checked: where it runs (its CPU, what scheduling it could not get, the PM QoS request); the
link's framing (any split of the stream, bad frames refused); the child answers
telegrams while the daemon's event loop is blocked, and the daemon's mirror then has every reply's
latency, the cycle count and the loop state; commands reach the loop and a target the child refuses
comes back as ``Faulted``; the child's log records reach the daemon's loggers; ``samples`` round
trips; and when the daemon dies (SIGKILL) or the child gets SIGTERM, the child sends ``Stop = 1``
with zero corrections and exits on its own — no motion from a loop nobody supervises.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pickle
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_daemon_executor import Clock, Grating, Robot, calibration
from test_rt_encoder_reader import Angles

from comp_daemon.daemon.rt_process import ReaderMirror, RealtimeProcess, RemoteRuntime
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import (
    EncoderFault,
    EncoderReaderConfig,
    EncoderReading,
    LinearGratingCalibration,
)
from comp_daemon.rt.encoder_reader import FaultKind as EncoderFaultKind
from comp_daemon.rt.link import FrameDecoder, LinkError, LoopStart, RtProcessError, RtStart, encode_frame
from comp_daemon.rt.loop import LoopRuntime
from comp_daemon.rt.rsi_codec import SenReply, build_rob, parse_sen
from comp_daemon.rt.rsi_server import RsiServerConfig
from comp_daemon.rt.safety import Faulted, FaultKind, SafetySettings, SafetyState
from comp_daemon.rt.scheduling import apply_scheduling, other_cpus, request_wakeup_latency, resolve_cpu
from comp_daemon.sim.converter import ConverterConfig, SimulatedConverter

HOME = (10.0, -90.0, 90.0, 0.0, 30.0, 0.0)

# ------------------------------------------------------------------------------------------ where it runs


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


def test_refused_scheduling_is_reported_not_fatal(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "sched_setaffinity", refuse)
    pinned, scheduler, notes = apply_scheduling(0, 20, who="the real-time process")
    assert pinned is None and scheduler == "normal"
    assert any("SCHED_FIFO" in n and "CAP_SYS_NICE" in n for n in notes), notes
    assert any("could not pin the real-time process to CPU 0" in n for n in notes), notes


def test_wakeup_latency_request_is_written_as_the_kernel_reads_it(tmp_path: Path) -> None:
    """The PM QoS request is an s32 held while the file is open; a refusal is a note, not an error."""
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    fh, note = request_wakeup_latency(0, str(device))
    assert fh is not None and note is None
    try:
        assert device.read_bytes() == struct.pack("i", 0)
    finally:
        fh.close()
    fh, note = request_wakeup_latency(0, "/nonexistent/cpu_dma_latency")
    assert fh is None and note is not None and "wake-up latency of 0 µs" in note


def test_loop_forecasts_the_next_telegram() -> None:
    clock = Clock()
    robot = Robot(clock)
    runtime = LoopRuntime(
        {j: Grating(robot, j) for j in (1, 2, 3)},
        calibration=calibration(),
        safety=SafetySettings(),
        loop=JointLoopSettings(),
        clock_ns=clock,
    )  # cycle 12 ms
    assert runtime.next_telegram_ns() is None  # none seen yet
    runtime.handle(robot.telegram())
    t0 = clock.ns
    assert runtime.next_telegram_ns() == t0 + 12_000_000
    clock.ns += 30_000_000  # two cycles missed: the one after
    assert runtime.next_telegram_ns() == t0 + 36_000_000
    clock.ns += 30_000_000  # five cycles without a telegram: RSI has stopped, no forecast
    assert runtime.next_telegram_ns() is None


# ------------------------------------------------------------------------------------------ framing


@given(
    messages=st.lists(
        st.recursive(
            st.none() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
            lambda kids: st.lists(kids, max_size=4).map(tuple) | st.dictionaries(st.text(max_size=5), kids),
            max_leaves=12,
        ),
        min_size=1,
        max_size=6,
    ),
    cuts=st.lists(st.integers(min_value=0, max_value=4000), max_size=8),
)
@settings(max_examples=150, deadline=None)
def test_frames_survive_any_split_of_the_stream(messages: list[object], cuts: list[int]) -> None:
    stream = b"".join(encode_frame(m) for m in messages)
    points = sorted({c % (len(stream) + 1) for c in cuts})
    decoder = FrameDecoder()
    out: list[object] = []
    start = 0
    for p in [*points, len(stream)]:
        out.extend(decoder.feed(stream[start:p]))
        start = p
    assert out == messages


def test_bad_frames_are_refused_with_the_reason() -> None:
    with pytest.raises(LinkError, match="limit"):
        FrameDecoder().feed((1 << 31).to_bytes(4, "big"))
    payload = b"not a pickle"
    with pytest.raises(LinkError, match="unreadable frame of 12 bytes"):
        FrameDecoder().feed(len(payload).to_bytes(4, "big") + payload)


def test_reader_mirror_ages_and_turns_stale_without_reports() -> None:
    now = [1_000_000_000]
    mirror = ReaderMirror(2, stale_after_ms=36.0, clock_ns=lambda: now[0])
    first = mirror.reading()
    assert isinstance(first, EncoderFault) and first.kind is EncoderFaultKind.NO_DATA
    mirror.update(EncoderReading(2, 1.5, 1234, now[0] - 2_000_000, 2_000_000, False), now[0])
    now[0] += 10_000_000
    r = mirror.reading()
    assert isinstance(r, EncoderReading) and r.age_ns == 12_000_000  # aged by the time since
    now[0] += 30_000_000  # no report for 40 ms: the mirror does not pretend the grating is fresh
    r = mirror.reading()
    assert isinstance(r, EncoderFault) and r.kind is EncoderFaultKind.STALE and "42.0 ms" in r.detail


# ------------------------------------------------------------------------------------------ the child


class Controller:
    """A blocking UDP client in the test standing in for the robot controller."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.address = address
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(1.0)
        self.ipoc = 1000

    def cycle(self, axes: tuple[float, ...] = HOME) -> SenReply:
        self.ipoc += 12
        self.sock.sendto(build_rob(self.ipoc, axes, axes), self.address)
        reply = parse_sen(self.sock.recv(65536))
        assert reply.ipoc == self.ipoc
        return reply

    def run(self, n: int, period_s: float = 0.012) -> list[SenReply]:
        out = []
        for _ in range(n):
            out.append(self.cycle())
            time.sleep(period_s)
        return out

    def close(self) -> None:
        self.sock.close()


def loop_start(port: str) -> LoopStart:
    reader = EncoderReaderConfig(port=port, joint=1, backoff_initial_ms=20.0, backoff_max_ms=100.0)
    return LoopStart(
        readers=((reader, LinearGratingCalibration(1000.0)),),
        calibration=None,
        safety=SafetySettings(),
        loop=JointLoopSettings(cycle_s=0.012),
    )


@pytest.fixture
async def rtp(tmp_path: Path) -> AsyncIterator[RealtimeProcess]:
    proc = RealtimeProcess(
        RtStart(rsi=RsiServerConfig(controller_host="127.0.0.1", bind_port=0), push_period_s=0.01)
    )
    await proc.start()
    await proc.start_loop(loop_start(str(tmp_path / "no-such-grating")))
    yield proc
    code = await proc.stop()
    assert code == 0


def controller_of(rtp: RealtimeProcess) -> Controller:
    host, port = rtp.info["rsi_address"]
    return Controller((host, port))


async def until(cond: object, timeout_s: float = 5.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():  # type: ignore[operator]
            await asyncio.sleep(0.01)


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
async def test_the_child_pins_itself_and_says_what_it_got(tmp_path: Path) -> None:
    cpu = sorted(os.sched_getaffinity(0))[0]
    before = os.sched_getaffinity(0)
    proc = RealtimeProcess(RtStart(rsi=RsiServerConfig(controller_host="127.0.0.1", bind_port=0), cpu=cpu))
    await proc.start()
    try:
        assert proc.proc is not None
        assert os.sched_getaffinity(proc.proc.pid) == {cpu}
        d = proc.describe()
        assert d["pid"] == proc.proc.pid and d["cpu"] == cpu and d["scheduler"] == "normal"
        assert os.sched_getaffinity(0) == before  # the daemon keeps its CPUs
    finally:
        assert await proc.stop() == 0


async def test_child_answers_while_the_daemon_loop_is_blocked(rtp: RealtimeProcess) -> None:
    assert rtp.proc is not None and rtp.proc.pid != os.getpid() and rtp.alive
    ctl = controller_of(rtp)
    replies: list[SenReply] = []
    client = threading.Thread(target=lambda: replies.extend(ctl.run(30)))
    client.start()
    time.sleep(0.5)  # the daemon's event loop does nothing for 0.5 s: no reply may depend on it
    client.join(5.0)
    ctl.close()
    assert len(replies) == 30 and all(not r.stop and r.ak_deg == (0.0,) * 6 for r in replies)
    runtime = rtp.runtime
    assert runtime is not None
    await until(lambda: rtp.rsi_stats.answered == 30 and runtime.telegrams == 30)
    assert rtp.rsi_stats.latency.count == 30 and rtp.rsi_stats.handler_errors == 0
    assert len(runtime.trace) == 30 and runtime.last_ipoc == ctl.ipoc
    assert runtime.last_actual_deg == HOME
    age = rtp.report_age_s()
    assert age is not None and age < 1.0
    # the grating port does not exist: the mirror says so, and a target could not start
    reasons = runtime.readiness_reasons()
    assert any("grating A1: gone" in r for r in reasons), reasons


async def test_commands_reach_the_loop_and_a_refused_target_comes_back_faulted(rtp: RealtimeProcess) -> None:
    runtime = rtp.runtime
    assert isinstance(runtime, RemoteRuntime)
    runtime.arm("t1", HOME, (HOME[0],))
    assert runtime.core.state is SafetyState.ARMED  # mirrored at once
    await until(lambda: runtime.core.state is SafetyState.ARMED and rtp.last_report_ns is not None)
    runtime.release()
    await until(lambda: runtime.core.state is SafetyState.IDLE)

    # a stop fault latched in the child that the mirror has not seen yet: the mirror accepts the
    # target, the child refuses it and reports Faulted for it
    rtp.command("fault", FaultKind.CORRECTION_LIMIT, "latched behind the mirror's back")
    runtime.arm("t2", HOME, (HOME[0],))
    async with asyncio.timeout(5):
        while True:
            event = await runtime.next_event()
            if isinstance(event, Faulted) and event.target_id == "t2":
                break
    assert "the loop refused the target" in event.fault.detail
    await until(lambda: runtime.core.state is SafetyState.FAULT)
    assert runtime.core.fault is not None and runtime.core.fault.kind is FaultKind.CORRECTION_LIMIT
    runtime.reset()
    await until(lambda: runtime.core.state is SafetyState.IDLE)


async def test_the_mirror_shows_the_fault_when_its_event_arrives(rtp: RealtimeProcess) -> None:
    """The executor acts on a ``Faulted`` event at once (finishes the target, checks readiness,
    claims the next): when the daemon reads the event, its mirror must already show the state the
    event came from, not the one before it (the report used to follow the event, and a busy
    machine could hold it back long enough for the next target to be claimed)."""
    runtime = rtp.runtime
    assert isinstance(runtime, RemoteRuntime)
    seen: list[tuple[object, SafetyState, FaultKind | None]] = []

    def on_event(event: object) -> None:
        core = runtime.core
        seen.append((event, core.state, None if core.fault is None else core.fault.kind))
        RemoteRuntime.on_event(runtime, event)  # type: ignore[arg-type]

    runtime.on_event = on_event  # type: ignore[method-assign]
    # armed with no telegrams coming: the loop's own timer faults the target (RSI lost) in the
    # child, behind the mirror's back
    runtime.arm("t1", HOME, (HOME[0],))
    async with asyncio.timeout(5):
        event = await runtime.next_event()
    assert isinstance(event, Faulted) and event.target_id == "t1"
    assert event.fault.kind is FaultKind.RSI_LOST
    assert seen[0][1:] == (SafetyState.FAULT, FaultKind.RSI_LOST), seen
    runtime.release()
    runtime.reset()
    await until(lambda: runtime.core.state is SafetyState.IDLE)


async def test_close_waits_for_stop_replies_counted_in_the_child(rtp: RealtimeProcess) -> None:
    """A slow controller (a telegram every 40 ms, as on a loaded machine): the endpoint stays open
    until the grace replies with ``Stop = 1`` have gone out, and the daemon has the final state
    (last reply ``Stop = 1``, zero steps) when ``close_rsi`` returns."""
    runtime = rtp.runtime
    assert runtime is not None
    ctl = controller_of(rtp)
    replies: list[SenReply] = []

    def slow_controller() -> None:
        with contextlib.suppress(TimeoutError, OSError):
            for _ in range(40):
                replies.append(ctl.cycle())
                time.sleep(0.04)

    client = threading.Thread(target=slow_controller)
    client.start()
    try:
        await until(lambda: runtime.telegrams >= 2 and runtime.rsi_alive())
        runtime.shutdown()
        await rtp.close_rsi(3)
        assert runtime.last_stop is True and runtime.last_ak_deg == (0.0,) * 6
        assert runtime.replies_after_shutdown >= 3
    finally:
        await asyncio.to_thread(client.join, 10.0)
        ctl.close()
    stops = [r for r in replies if r.stop]
    assert len(stops) >= 3 and all(r.ak_deg == (0.0,) * 6 for r in stops)
    assert len(replies) < 40  # the endpoint closed after them


async def test_a_frozen_child_still_gives_the_controller_its_stop_replies(rtp: RealtimeProcess) -> None:
    """The real-time process is not scheduled for 0.8 s right after the close began (a loaded
    machine) while the controller keeps sending every 12 ms: when it runs again it goes on
    answering ``Stop = 1`` until the grace replies are out, rather than closing because a clock
    ran out while it could not answer."""
    runtime = rtp.runtime
    assert runtime is not None and rtp.proc is not None
    ctl = controller_of(rtp)
    ctl.sock.setblocking(False)
    replies: list[SenReply] = []
    sending = threading.Event()
    sending.set()

    def controller() -> None:  # sends on its own schedule, whether replies come or not
        while sending.is_set():
            ctl.ipoc += 12
            with contextlib.suppress(OSError):
                ctl.sock.sendto(build_rob(ctl.ipoc, HOME, HOME), ctl.address)
            time.sleep(0.012)
            with contextlib.suppress(BlockingIOError, OSError):
                while True:
                    replies.append(parse_sen(ctl.sock.recv(65536)))

    client = threading.Thread(target=controller)
    client.start()
    grace = 10
    try:
        await until(lambda: runtime.telegrams >= 2 and runtime.rsi_alive())
        runtime.shutdown()
        closing = asyncio.create_task(rtp.close_rsi(grace))
        await asyncio.sleep(0.02)
        os.kill(rtp.proc.pid, signal.SIGSTOP)
        await asyncio.sleep(0.8)
        os.kill(rtp.proc.pid, signal.SIGCONT)
        await closing
        assert runtime.last_stop is True and runtime.replies_after_shutdown >= grace
    finally:
        os.kill(rtp.proc.pid, signal.SIGCONT)
        await asyncio.sleep(0.2)
        sending.clear()
        await asyncio.to_thread(client.join, 10.0)
        ctl.close()
    stops = [r for r in replies if r.stop]
    assert len(stops) >= grace and all(r.ak_deg == (0.0,) * 6 for r in stops)


async def test_child_logs_reach_the_daemon_loggers(
    rtp: RealtimeProcess, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="comp_daemon.rt.rsi_server")
    host, port = rtp.info["rsi_address"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(b"<Rob><IPOC>not a number</IPOC></Rob>", (host, port))
    await until(lambda: any("garbled telegram" in r.getMessage() for r in caplog.records))
    await until(lambda: rtp.rsi_stats.garbled == 1)
    # the child's own structlog records take the same way
    caplog.set_level(logging.ERROR, logger="comp_daemon.rt.child")
    assert rtp.link.send(("bogus", 1))
    await until(
        lambda: any(
            r.name == "comp_daemon.rt.child"
            and "rt: unknown message 'bogus' from the daemon" in r.getMessage()
            for r in caplog.records
        )
    )


def _epoll_sets(pid: int) -> list[set[str]]:
    """What each epoll instance of process ``pid`` watches: the targets of the watched descriptors
    (``/dev/pts/3``, ``socket:[1234]``, …), from ``/proc/PID/fdinfo``."""
    sets = []
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):
            if os.readlink(f"/proc/{pid}/fd/{fd}") != "anon_inode:[eventpoll]":
                continue
            info = Path(f"/proc/{pid}/fdinfo/{fd}").read_text()
            watched = set()
            for line in info.splitlines():
                if line.startswith("tfd:"):
                    with contextlib.suppress(OSError):
                        watched.add(os.readlink(f"/proc/{pid}/fd/{int(line.split()[1])}"))
            sets.append(watched)
    return sets


def _udp_socket(pid: int, port: int) -> str:
    """``socket:[inode]`` of the UDP socket bound to ``port`` in process ``pid``."""
    for line in Path(f"/proc/{pid}/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if int(fields[1].split(":")[1], 16) == port:
            return f"socket:[{fields[9]}]"
    raise AssertionError(f"no UDP socket on port {port}")


@pytest.mark.skipif(not Path("/proc/self/fdinfo").is_dir(), reason="Linux /proc")
async def test_the_rsi_endpoint_never_waits_on_a_grating_tty(tmp_path: Path) -> None:
    """A tty poll can wait in the kernel for a normal-priority worker (flush_work in n_tty_poll):
    the event loop that answers RSI must not poll the gratings' ttys, only the readers' own may."""
    conv = SimulatedConverter(
        ConverterConfig(1, 1000.0, 0.0, link_path=str(tmp_path / "grating-j1")), Angles()
    )
    conv.start()
    proc = RealtimeProcess(RtStart(rsi=RsiServerConfig(controller_host="127.0.0.1", bind_port=0)))
    await proc.start()
    try:
        await proc.start_loop(loop_start(conv.port))
        assert proc.proc is not None
        pid, tty = proc.proc.pid, os.path.realpath(conv.port)
        rsi = _udp_socket(pid, proc.info["rsi_address"][1])
        await until(lambda: conv.replies >= 20 and any(tty in s for s in _epoll_sets(pid)), 10.0)
        sets = _epoll_sets(pid)
        assert [s for s in sets if rsi in s and tty in s] == [], sets
        assert any(rsi in s for s in sets) and any(tty in s for s in sets), sets
        ctl = controller_of(proc)
        assert len(ctl.run(10)) == 10  # and the endpoint answers meanwhile
        ctl.close()
    finally:
        assert await proc.stop() == 0
        conv.close()


async def test_samples_round_trip(rtp: RealtimeProcess) -> None:
    runtime = rtp.runtime
    assert runtime is not None
    ctl = controller_of(rtp)
    client = threading.Thread(target=lambda: ctl.run(10))
    client.start()
    try:
        samples = await runtime.samples(4, timeout_s=3.0)
    finally:
        await asyncio.to_thread(client.join, 5.0)
        ctl.close()
    assert len(samples) == 4 and all(s.actual_deg == HOME and s.counts == (None,) for s in samples)
    with pytest.raises(TimeoutError):
        await runtime.samples(1, timeout_s=0.1)  # no telegrams now


async def test_a_dead_child_fails_the_active_target_and_tells_the_daemon(tmp_path: Path) -> None:
    lost: list[str] = []
    rtp = RealtimeProcess(
        RtStart(rsi=RsiServerConfig(controller_host="127.0.0.1", bind_port=0)), on_lost=lost.append
    )
    await rtp.start()
    runtime = await rtp.start_loop(loop_start(str(tmp_path / "no-such-grating")))
    runtime.arm("t1", HOME, (HOME[0],))
    assert rtp.proc is not None
    rtp.proc.kill()
    async with asyncio.timeout(5):
        event = await runtime.next_event()
    assert isinstance(event, Faulted) and event.target_id == "t1"
    assert event.fault.kind is FaultKind.RSI_LOST and "the real-time process has gone" in event.fault.detail
    assert lost and not rtp.alive
    assert any("the real-time process has gone" in r for r in runtime.readiness_reasons())
    with pytest.raises(RtProcessError, match="has gone"):
        runtime.arm("t2", HOME, (HOME[0],))  # refused by the mirror (fault) or by the dead link
    assert await rtp.stop() == -signal.SIGKILL


# ------------------------------------------------------------------------------------------ going safe

_PARENT = textwrap.dedent(
    """
    import asyncio, sys
    from comp_daemon.daemon.rt_process import RealtimeProcess
    from comp_daemon.rt.link import RtStart
    from comp_daemon.rt.rsi_server import RsiServerConfig
    from test_rt_process import loop_start

    async def main():
        rtp = RealtimeProcess(RtStart(rsi=RsiServerConfig(controller_host="127.0.0.1", bind_port=0),
                                      grace_cycles=3))
        host, port = await rtp.start()
        runtime = await rtp.start_loop(loop_start(sys.argv[1]))
        runtime.arm("t1", (10.0, -90.0, 90.0, 0.0, 30.0, 0.0), (10.0,))
        print(port, rtp.proc.pid, flush=True)
        await asyncio.sleep(3600)

    asyncio.run(main())
    """
)


def pid_gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.02)
    return False


@pytest.mark.parametrize("who", ["daemon killed", "child SIGTERM"])
def test_the_child_goes_safe_on_its_own(tmp_path: Path, who: str) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), *sys.path]))
    parent = subprocess.Popen(
        [sys.executable, "-c", _PARENT, str(tmp_path / "no-such-grating")],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert parent.stdout is not None
        port_s, child_s = parent.stdout.readline().split()
        child_pid = int(child_s)
        ctl = Controller(("127.0.0.1", int(port_s)))
        before = ctl.run(10)
        assert not any(r.stop for r in before)
        if who == "daemon killed":
            parent.send_signal(signal.SIGKILL)
            parent.wait(5)
        else:
            os.kill(child_pid, signal.SIGTERM)
        after: list[SenReply] = []
        for _ in range(40):
            try:
                after.append(ctl.cycle())
            except (TimeoutError, ConnectionRefusedError):
                break
            time.sleep(0.012)
        ctl.close()
        # from the first reply after the loss on: Stop = 1 and no correction, then silence
        stops = [r for r in after if r.stop]
        assert len(stops) >= 3, after
        assert all(r.ak_deg == (0.0,) * 6 for r in after)
        first_stop = after.index(stops[0])
        assert all(r.stop for r in after[first_stop:])
        assert len(after) < 40  # the endpoint closed
        assert pid_gone(child_pid, 5.0)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(5)
        if parent.stdout is not None:
            parent.stdout.close()


@pytest.mark.parametrize("fd", ["0", "987"])
def test_the_child_started_by_hand_says_what_it_needs(fd: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "comp_daemon.rt.child", "--fd", fd],
        capture_output=True,
        text=True,
        timeout=30,
        stdin=subprocess.DEVNULL,
    )
    assert r.returncode == 2
    assert (
        f"--fd {fd}: not the daemon's socket pair" in r.stderr
        and "the daemon starts this process" in r.stderr
    )


def test_messages_pickle_under_their_importable_names() -> None:
    spec = loop_start("/dev/null")
    assert pickle.loads(pickle.dumps(spec)) == spec
    assert type(pickle.loads(pickle.dumps(spec))).__module__ == "comp_daemon.rt.link"
