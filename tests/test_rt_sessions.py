"""The controller session at the RSI endpoint, over real UDP between processes.

The daemon's real-time process (``comp_daemon.rt.child``, started by :class:`RealtimeProcess`)
answers the simulated KR C4; other processes play the network and the cell's other devices:

- a relay that delivers every telegram and, 30 ms later, a copy of it (a switch that duplicates,
  a path that delays): only the session's newest telegram is answered, never a copy of an older
  one, the controller keeps RSI running, and the copies are counted up to ``/api/status`` and
  ``/metrics``;
- a second sender on the controller's address: never answered, never fed into the loop, counted;
- a controller restart (new source port, IPOC back to a small number): a new session, logged,
  counted and recorded as ``rsi.restarted``.

The plain-socket cases (a copy queued right behind the current telegram, the same port coming back
with its IPOC gone back) pin the rule down without timing.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from test_rt_process import loop_start, until
from test_rt_rsi_server import (
    AK,
    MakeServer,
    _StillPlant,
    controller_sock,  # noqa: F401  (fixture)
    make_server,  # noqa: F401  (fixture)
    nothing_arrives,
    recv,
    telegram,
)

from comp_daemon.daemon.rsi_sessions import RsiSessions
from comp_daemon.daemon.rt_process import RealtimeProcess
from comp_daemon.rt.link import RtStart
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, parse_sen
from comp_daemon.rt.rsi_server import RsiServerConfig
from comp_daemon.service import metrics
from comp_daemon.sim.rsi_controller import RsiControllerConfig, RsiState, SimulatedRsiController

CYCLE_MS = 12


@pytest.fixture
async def rtp(tmp_path: Path) -> AsyncIterator[RealtimeProcess]:
    proc = RealtimeProcess(
        RtStart(
            rsi=RsiServerConfig(controller_host="127.0.0.1", bind_port=0, cycle_ms=float(CYCLE_MS)),
            push_period_s=0.01,
        )
    )
    await proc.start()
    await proc.start_loop(loop_start(str(tmp_path / "no-such-grating")))
    yield proc
    assert await proc.stop() == 0


def controller(port: int, ipoc_start: int = 1_000_000) -> SimulatedRsiController:
    """The simulated KR C4 in this test process, with kuka_experimental's Timeout of 100 late
    replies: on a loaded 2-core machine this process (and the child) can go unscheduled for more
    than the default 10 cycles, which is not what these tests are about; what they check of the
    replies does not depend on it."""
    config = RsiControllerConfig(
        server_port=port, cycle_ms=CYCLE_MS, ipoc_start=ipoc_start, timeout_count=100
    )
    return SimulatedRsiController(config, _StillPlant())


def rejected(reason: str) -> float:
    return metrics.REGISTRY.get_sample_value("comp_daemon_rsi_rejected_total", {"reason": reason}) or 0.0


class Recorder:
    def __init__(self) -> None:
        self.events: list[tuple[str, dict[str, Any]]] = []

    async def __call__(self, kind: str, message: dict[str, Any]) -> None:
        self.events.append((kind, message))


# ------------------------------------------------------------------------------------------ late copies

_DUPLICATING_RELAY = """
import heapq, json, re, select, socket, sys, time
listen, daemon_port = int(sys.argv[1]), int(sys.argv[2])
delay_s, seconds = float(sys.argv[3]), float(sys.argv[4])
ipoc_re = re.compile(rb"<IPOC>(\\d+)</IPOC>")
ctrl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
ctrl.bind(("127.0.0.1", listen))
up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
up.bind(("127.0.0.1", 0))
daemon = ("127.0.0.1", daemon_port)
print(json.dumps({"ready": True}), flush=True)
copies, controller = [], None
forwarded = copies_sent = 0
replies = []
end = time.monotonic() + seconds
poller = select.poll()
poller.register(ctrl, select.POLLIN)
poller.register(up, select.POLLIN)
while time.monotonic() < end:
    now = time.monotonic()
    while copies and copies[0][0] <= now:
        up.sendto(heapq.heappop(copies)[2], daemon)
        copies_sent += 1
    wait_ms = 5 if not copies else max(0, int((copies[0][0] - now) * 1000))
    for fd, _ in poller.poll(wait_ms):
        if fd == ctrl.fileno():
            data, controller = ctrl.recvfrom(65536)
            up.sendto(data, daemon)
            forwarded += 1
            heapq.heappush(copies, (time.monotonic() + delay_s, forwarded, data))
        else:
            data, _ = up.recvfrom(65536)
            if controller is not None:
                ctrl.sendto(data, controller)
            m = ipoc_re.search(data)
            replies.append(int(m.group(1)) if m else -1)
backwards = sum(1 for a, b in zip(replies, replies[1:]) if b <= a)
print(json.dumps(dict(forwarded=forwarded, copies=copies_sent, replies=len(replies), backwards=backwards)))
"""


async def test_late_copies_are_never_answered_and_rsi_keeps_running(rtp: RealtimeProcess) -> None:
    """Every telegram arrives twice, the copy 30 ms late: each reply is for a newer IPOC than the
    one before (answering the copies sent replies for cycles the controller had left, and one
    arriving behind the current telegram was answered instead of it: RSI stopped on late replies),
    the controller runs on, and the copies are counted in the daemon's view, its status and
    metrics."""
    _, daemon_port = rtp.info["rsi_address"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        relay_port = s.getsockname()[1]
    seconds = 4.0
    relay = await asyncio.create_subprocess_exec(
        sys.executable, "-c", _DUPLICATING_RELAY, str(relay_port), str(daemon_port), "0.030", str(seconds),
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert relay.stdout is not None
    assert json.loads(await asyncio.wait_for(relay.stdout.readline(), 30))["ready"]
    ctl = controller(relay_port)
    sessions = RsiSessions(timeout_count=10)
    stale_before = rejected("stale_copy")
    await ctl.start()
    try:
        out, _ = await asyncio.wait_for(relay.communicate(), seconds + 30)
        state, stops = ctl.state, list(ctl.stats.stops)
    finally:
        await ctl.close()
    seen = json.loads(out.splitlines()[-1])
    assert state is RsiState.RUNNING, stops  # no stop on late replies
    assert seen["backwards"] == 0, seen  # no reply for an IPOC older than one already answered
    assert seen["copies"] > 0.8 * seen["forwarded"] > 100, seen
    stats = rtp.rsi_stats  # the daemon's copy, from the state reports
    await until(lambda: stats.stale >= seen["copies"] - 5)
    assert stats.other_sender == 0 and stats.sessions == 1
    assert stats.answered + stats.superseded >= seen["forwarded"] - 5
    runtime = rtp.runtime
    assert runtime is not None
    await sessions.observe(runtime, stats, report_age_s=0.0)
    print(f"late copies: relay {seen}, endpoint {stats.snapshot() | {'latency': None, 'jitter': None}}")
    assert sessions.report()["stale_copies"] == stats.stale  # /api/status, under "rsi"
    assert rejected("stale_copy") - stale_before == stats.stale  # /metrics


async def test_a_copy_queued_behind_the_current_telegram_is_not_answered(
    make_server: MakeServer,  # noqa: F811
    controller_sock: socket.socket,  # noqa: F811
) -> None:
    seen: list[int] = []

    def handler(t: RobTelegram) -> SenReply:
        seen.append(t.ipoc)
        return SenReply(t.ipoc, AK)

    _, proto, addr = await make_server(handler)
    controller_sock.sendto(telegram(1012), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 1012
    for ipoc in (1024, 1036, 1012):  # the current telegrams, then a late copy of one answered
        controller_sock.sendto(telegram(ipoc), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 1036
    controller_sock.sendto(telegram(1024), addr)  # a late copy on its own
    assert await nothing_arrives(controller_sock)
    assert seen == [1012, 1036]
    s = proto.stats
    assert (s.answered, s.superseded, s.stale, s.sessions) == (2, 1, 2, 1)


# ------------------------------------------------------------------------------------------ sessions

_SECOND_SENDER = """
import json, socket, sys, time
from comp_daemon.rt.rsi_codec import build_rob
port, seconds = int(sys.argv[1]), float(sys.argv[2])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
s.setblocking(False)
axes = (0.0, -90.0, 90.0, 0.0, 45.0, 0.0)
sent = replies = 0
t0 = time.monotonic()
while time.monotonic() - t0 < seconds:
    s.sendto(build_rob(9_000_000 + 4 * sent, axes, axes), ("127.0.0.1", port))
    sent += 1
    time.sleep(0.004)
    while True:
        try:
            s.recv(65536)
            replies += 1
        except BlockingIOError:
            break
print(json.dumps({"sent": sent, "replies": replies}))
"""


async def test_a_second_sender_is_never_answered_nor_fed_into_the_loop(
    rtp: RealtimeProcess, caplog: pytest.LogCaptureFixture
) -> None:
    """While the controller runs its session, another process on its address sends valid telegrams
    (higher IPOCs, every 4 ms): none is answered (479 of 482 were), none reaches the loop, all are
    counted, the controller runs on, and the operator reads the second sender's address in the log."""
    caplog.set_level(logging.WARNING, logger="comp_daemon.rt.rsi_server")
    _, port = rtp.info["rsi_address"]
    ctl = controller(port)
    await ctl.start()
    sender = "{}:{}".format(*ctl.local_address)
    try:
        await until(lambda: rtp.rsi_stats.answered > 10)
        other = await asyncio.create_subprocess_exec(
            sys.executable, "-c", _SECOND_SENDER, str(port), "3.0", stdout=asyncio.subprocess.PIPE
        )
        out, _ = await asyncio.wait_for(other.communicate(), 60)
        state = ctl.state
    finally:
        await ctl.close()
    second = json.loads(out)
    assert second["replies"] == 0 and second["sent"] > 300, second
    assert state is RsiState.RUNNING, list(ctl.stats.stops)
    stats, runtime = rtp.rsi_stats, rtp.runtime
    assert runtime is not None
    await until(lambda: stats.other_sender >= second["sent"] - 5)
    assert stats.sessions == 1 and stats.session_sender == sender
    assert all(ipoc < 9_000_000 for _, ipoc, *_ in runtime.trace)  # the loop saw one controller
    assert any("second sender 127.0.0.1:" in r.getMessage() for r in caplog.records)
    print(f"second sender: {second}, other_sender {stats.other_sender}, answered {stats.answered}")


async def test_a_controller_restart_is_a_new_session_logged_counted_and_recorded(
    rtp: RealtimeProcess, caplog: pytest.LogCaptureFixture
) -> None:
    """The controller stops and a new one starts 0.6 s later from another port with its IPOC back
    at 1 000, and the daemon's session watch did not look in between (a restart faster than it
    saw telegrams cease): the new one is answered, and the daemon logs, counts and records the new
    session (it used to run on as the same one, without a word)."""
    caplog.set_level(logging.INFO, logger="comp_daemon")
    _, port = rtp.info["rsi_address"]
    events = Recorder()
    sessions = RsiSessions(timeout_count=10, record_event=events)
    stats, runtime = rtp.rsi_stats, rtp.runtime
    assert runtime is not None
    sessions_before = metrics.REGISTRY.get_sample_value("comp_daemon_rsi_sessions_total") or 0.0
    first = controller(port)
    await first.start()
    await until(lambda: stats.answered > 20)
    await sessions.observe(runtime, stats, report_age_s=0.0)
    first_sender = "{}:{}".format(*first.local_address)
    await first.close()
    await asyncio.sleep(0.6)
    second = controller(port, ipoc_start=1_000)
    await second.start()
    second_sender = "{}:{}".format(*second.local_address)
    try:
        await until(lambda: stats.sessions == 2 and second.stats.replies_ok > 20)
        await sessions.observe(runtime, stats, report_age_s=0.0)
        state, late = second.state, second.stats.late_total
    finally:
        await second.close()
    assert state is RsiState.RUNNING and late <= 2
    assert stats.session_sender == second_sender != first_sender
    report = sessions.report()
    assert (report["sessions"], report["restarts"]) == (2, 1), report
    assert report["sender"] == stats.session_sender
    kinds = [k for k, _ in events.events]
    assert kinds == ["rsi.restarted"], kinds
    message = events.events[0][1]
    assert message["sender"] == stats.session_sender and message["previous_sender"] == first_sender
    after = metrics.REGISTRY.get_sample_value("comp_daemon_rsi_sessions_total") or 0.0
    assert after - sessions_before == 2
    lines = [r.getMessage() for r in caplog.records if "controller session 2" in r.getMessage()]
    assert lines and "IPOC went back" not in lines[0] and first_sender in lines[0], lines
    print(f"restart: {lines[0]}; second controller: {second.status()['replies_ok']} replies ok, {late} late")


async def test_the_same_port_back_with_its_ipoc_gone_back_is_a_new_session(
    make_server: MakeServer,  # noqa: F811
    controller_sock: socket.socket,  # noqa: F811
) -> None:
    """An IPOC that went back is a stale copy while the session's sender is sending, and a restart
    of that sender once it has been silent for ``session_silence_ms``."""
    started: list[int] = []
    _, proto, addr = await make_server(session_silence_ms=60.0, cycle_ms=12.0)
    proto.on_new_session = lambda n, sender, what: started.append(n)
    for ipoc in (5000, 5012):
        controller_sock.sendto(telegram(ipoc), addr)
        assert parse_sen(await recv(controller_sock)).ipoc == ipoc
    controller_sock.sendto(telegram(12), addr)
    assert await nothing_arrives(controller_sock, 0.01)  # within the silence: a stale copy
    await asyncio.sleep(0.1)
    controller_sock.sendto(telegram(24), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 24
    controller_sock.sendto(telegram(36), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 36
    assert (proto.stats.sessions, proto.stats.stale, started) == (2, 1, [1, 2])


def test_a_new_session_faults_the_active_target_and_leaves_an_idle_loop_alone() -> None:
    """The restarted controller holds another correction than the loop has summed up: a target
    in progress is failed (``rsi_lost``, freeze) before the new session's first telegram; with no
    target the new session simply begins."""
    from test_daemon_executor import JOINTS, Clock, Grating, Robot, calibration

    from comp_daemon.rt.controller import JointLoopSettings
    from comp_daemon.rt.loop import LoopRuntime
    from comp_daemon.rt.safety import Faulted, FaultKind, SafetySettings, SafetyState

    clock = Clock()
    robot = Robot(clock)
    runtime = LoopRuntime(
        {j: Grating(robot, j) for j in JOINTS},
        calibration=calibration(),
        safety=SafetySettings(),
        loop=JointLoopSettings(),
        clock_ns=clock,
    )
    runtime.handle(robot.telegram())
    runtime.new_session("controller session 2 from 127.0.0.1:40000")
    assert runtime.core.state is SafetyState.IDLE and runtime.events.empty()
    home = tuple(robot.setpoint)
    runtime.arm("t1", home, tuple(home[j - 1] for j in JOINTS))
    clock.ns += 12_000_000
    runtime.handle(robot.telegram())
    assert runtime.core.state in (SafetyState.ARMED, SafetyState.CORRECTING)
    runtime.new_session("controller session 2 from 127.0.0.1:40000")
    core = runtime.core
    assert core.state is SafetyState.FAULT and core.fault is not None
    assert core.fault.kind is FaultKind.RSI_LOST and "new RSI session" in core.fault.detail
    events = []
    while not runtime.events.empty():
        events.append(runtime.events.get_nowait())
    assert any(isinstance(e, Faulted) and e.target_id == "t1" for e in events), events
