"""The simulated controller re-arms RSI after a stop, as an operator restarting the program would,
and the daemon records each stop with the cause it reads from the wire, and each re-arm.

Real loopback UDP against misbehaving servers; the re-arm is timed by an injected clock, so the
test decides when the pause has passed, whatever the machine's load.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from test_sim_wire_rsi import RawServer, RigidPlant, until

from comp_daemon.daemon.rsi_sessions import STOP_CAUSES, RsiSessions
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, build_sen
from comp_daemon.rt.rsi_server import RsiServerStats
from comp_daemon.rt.safety import FaultKind, fault, new_core, shutdown
from comp_daemon.service import metrics
from comp_daemon.sim.rsi_controller import (
    RsiControllerConfig,
    RsiState,
    SimulatedRsiController,
    StopCause,
)


class ManualClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


Make = Callable[..., Any]


@pytest.fixture
async def make() -> AsyncIterator[Make]:
    closers: list[Callable[[], Any]] = []

    async def build(
        answer: Callable[[int, RobTelegram], bytes | None], clock: ManualClock, **cfg: Any
    ) -> tuple[SimulatedRsiController, RawServer]:
        raw = RawServer(answer)
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: raw, local_addr=("127.0.0.1", 0), family=socket.AF_INET
        )
        closers.append(transport.close)
        port = transport.get_extra_info("sockname")[1]
        controller = SimulatedRsiController(
            RsiControllerConfig(server_port=port, cycle_ms=4, **cfg), RigidPlant(), clock=clock
        )
        await controller.start()
        closers.append(controller.close)
        return controller, raw

    yield build
    for close in reversed(closers):
        result = close()
        if asyncio.iscoroutine(result):
            await result


def silent(n: int, t: RobTelegram) -> bytes | None:
    return None


def ok(n: int, t: RobTelegram) -> bytes | None:
    return build_sen(SenReply(t.ipoc))


async def test_late_reply_stop_rearms_after_the_pause_and_not_before(make: Make) -> None:
    clock = ManualClock()
    controller, raw = await make(silent, clock, timeout_count=3, rearm_after_s=5.0)
    await until(lambda: controller.state is RsiState.STOPPED)
    assert controller.stop_cause is StopCause.LATE_REPLIES
    assert controller.rearm_at == pytest.approx(clock.t + 5.0)
    sent = controller.stats.telegrams_sent
    await asyncio.sleep(0.1)  # 25 cycles with the pause not yet over: still stopped, silent
    assert controller.state is RsiState.STOPPED and controller.stats.telegrams_sent == sent
    assert controller.status()["rearm_in_s"] == pytest.approx(5.0)

    clock.t += 4.9
    await asyncio.sleep(0.05)
    assert controller.state is RsiState.STOPPED and controller.stats.sessions == 1

    clock.t += 0.2
    await until(lambda: controller.stats.sessions == 2)
    assert controller.stats.rearms == 1
    await until(lambda: controller.state is RsiState.STOPPED)  # still no replies: stops again
    stops = list(controller.stats.stops)
    assert [s.session for s in stops] == [1, 2]
    assert all(s.cause is StopCause.LATE_REPLIES and s.late == 3 and s.telegrams == 3 for s in stops)
    # the new session's telegrams start again at Delay 0, their IPOC kept counting meanwhile
    delays = [t.delay for t in raw.telegrams]
    assert delays == [0, 1, 2, 0, 1, 2]
    assert raw.telegrams[3].ipoc - raw.telegrams[2].ipoc > 4
    doc = controller.status()
    assert doc["sessions"] == 2 and doc["rearms"] == 1 and doc["stop_cause"] == "late_replies"
    assert [s["cause"] for s in doc["stops"]] == ["late_replies", "late_replies"]


async def test_rearmed_session_runs_on_when_replies_come_in_time(make: Make) -> None:
    clock = ManualClock()

    stopping = True

    def answer(n: int, t: RobTelegram) -> bytes | None:
        return build_sen(SenReply(t.ipoc, stop=stopping and n >= 3))  # the first session ends on Stop=1

    controller, _ = await make(answer, clock, timeout_count=100_000, rearm_after_s=1.0)
    await until(lambda: controller.state is RsiState.STOPPED)
    stopping = False
    clock.t += 1.0
    await until(lambda: controller.stats.sessions == 2)
    before = controller.stats.replies_ok
    await until(lambda: controller.stats.replies_ok >= before + 50)
    assert controller.state is RsiState.RUNNING and controller.stop_reason is None
    assert controller.stats.rearms == 1 and len(controller.stats.stops) == 1


async def test_rsi_off_and_no_rearm_setting_stay_stopped(make: Make) -> None:
    clock = ManualClock()
    controller, _ = await make(ok, clock, rearm_after_s=0.0)
    await until(lambda: controller.stats.replies_ok >= 5)
    controller.rsi_off()  # the robot program's RSI_OFF: an intended end, nothing to re-arm
    assert controller.stop_cause is StopCause.RSI_OFF and controller.rearm_at is None
    clock.t += 60.0
    await asyncio.sleep(0.05)
    assert controller.state is RsiState.STOPPED and controller.stats.sessions == 1

    plain, _ = await make(silent, clock, timeout_count=2)  # rearm_after_s None: as before, stays stopped
    await until(lambda: plain.state is RsiState.STOPPED)
    clock.t += 3600.0
    await asyncio.sleep(0.05)
    assert plain.state is RsiState.STOPPED and plain.rearm_at is None and plain.stats.sessions == 1


async def test_stop_request_from_the_sensor_is_recorded_and_rearmed(make: Make) -> None:
    clock = ManualClock()

    def answer(n: int, t: RobTelegram) -> bytes | None:
        return build_sen(SenReply(t.ipoc, stop=n >= 4))

    controller, _ = await make(answer, clock, rearm_after_s=2.0)
    await until(lambda: controller.state is RsiState.STOPPED)
    (stop,) = controller.stats.stops
    assert stop.cause is StopCause.SENSOR_STOP and stop.telegrams >= 4  # 4 unless a reply was late
    clock.t += 2.0
    await until(lambda: controller.stats.sessions == 2)


def test_rearm_pause_must_be_finite_and_not_negative() -> None:
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="rearm_after_s"):
            RsiControllerConfig(rearm_after_s=bad)


# ------------------------------------------------------------------ the daemon's record of the sessions


class WireView:
    """What the daemon's RSI session tracker reads of the loop: telegrams alive, core, last reply."""

    def __init__(self) -> None:
        self.alive = False
        self.core = new_core([1, 2])
        self.last_stop = False
        self.last_ipoc: int | None = None

    def rsi_alive(self) -> bool:
        return self.alive

    def telegram_age_s(self) -> float | None:
        return 0.5


class Recorded:
    def __init__(self) -> None:
        self.events: list[tuple[str, dict[str, Any]]] = []

    async def __call__(self, kind: str, message: dict[str, Any]) -> None:
        self.events.append((kind, message))


def session(view: WireView, stats: RsiServerStats, telegrams: int, late: int, delay: int | None) -> None:
    view.alive = True
    stats.answered += telegrams
    stats.late += late
    stats.controller_delay = delay
    view.last_ipoc = 1_000_000 + 12 * stats.answered


async def test_the_daemon_reads_each_stop_cause_from_the_wire() -> None:
    view, stats, events, clock = WireView(), RsiServerStats(16), Recorded(), ManualClock()
    sessions = RsiSessions(timeout_count=10, record_event=events, wall_clock=clock)
    runtime: Any = view

    async def run_and_stop(telegrams: int, late: int, delay: int | None) -> dict[str, Any]:
        clock.t += 5.0  # the pause before the session
        session(view, stats, telegrams, late, delay)
        await sessions.observe(runtime, stats)
        clock.t += 10.0
        view.alive = False
        await sessions.observe(runtime, stats)
        return sessions.stops[-1].to_dict()

    late = await run_and_stop(500, 4, 9)  # Delay 9 with Timeout 10: the next late reply stopped it
    assert late["cause"] == "late_replies" and late["cycles"] == 500 and late["late_replies"] == 10
    assert late["time"] == pytest.approx(clock.t - 0.5)  # when the last telegram came
    assert late["next"].startswith("on the robot: acknowledge the RSI message")

    ceased = await run_and_stop(300, 0, 2)  # telegrams ceased, no Stop=1, late count far from Timeout
    assert ceased["cause"] == "timeout" and ceased["cycles"] == 300 and ceased["late_replies"] == 2
    first = sessions.stops[0].to_dict()
    assert first["rearmed_at"] == pytest.approx(clock.t - 10.0) and first["pause_s"] == pytest.approx(5.5)
    assert first["next"] == "the robot controller re-armed RSI after 5.5 s"

    f = fault(view.core, FaultKind.DIVERGING, "A2 error grows", 1.0).core
    view.core, view.last_stop = f, True
    faulted = await run_and_stop(40, 0, 0)
    assert (
        faulted["cause"] == "fault"
        and "diverging" in faulted["detail"]
        and "A2 error grows" in faulted["detail"]
    )
    assert faulted["next"].startswith("acknowledge the fault here")

    view.core, view.last_stop = shutdown(view.core, 2.0).core, True
    shut = await run_and_stop(10, 0, 0)
    assert shut["cause"] == "operator" and shut["next"] == "none: the daemon is stopping"

    report = sessions.report()
    assert report["sessions"] == 4 and report["rearms"] == 3 and report["stops_total"] == 4
    assert report["stops_by_cause"] == {"late_replies": 1, "timeout": 1, "fault": 1, "operator": 1}
    assert [s["cause"] for s in report["stops"]] == ["operator", "fault", "timeout", "late_replies"]
    assert [k for k, _ in events.events] == ["rsi.stopped", *["rsi.rearmed", "rsi.stopped"] * 3]
    assert set(STOP_CAUSES) == set(metrics.RSI_STOP_CAUSES)


async def test_the_simulated_controller_names_the_cause_and_the_rearm() -> None:
    view, stats, clock = WireView(), RsiServerStats(16), ManualClock()
    answers = [
        {
            "state": "stopped",
            "stop_cause": "sensor_stop",
            "stop_reason": "Stop=1 from the sensor",
            "rearm_after_s": 5.0,
        }
    ]

    async def controller_status() -> dict[str, Any]:
        return answers[-1]

    sessions = RsiSessions(timeout_count=10, controller_status=controller_status, wall_clock=clock)
    runtime: Any = view
    session(view, stats, 100, 0, 0)
    await sessions.observe(runtime, stats)
    view.alive = False
    await sessions.observe(runtime, stats)
    stop = sessions.stops[-1]
    assert stop.cause == "fault" and stop.detail == "controller: Stop=1 from the sensor"
    assert stop.next == "the simulated controller re-arms RSI in 5 s"
    assert sessions.report()["next"] == stop.next
    # telegrams that waited in the socket arrive while the controller still has RSI stopped: no re-arm
    view.alive = True
    await sessions.observe(runtime, stats)
    assert not sessions.report()["running"] and sessions.rearms == 0
    assert sessions.stops[-1].next == "the simulated controller re-arms RSI in 5 s"
    clock.t += 5.2
    answers.append({"state": "running", "stop_cause": None, "stop_reason": None, "rearm_after_s": 5.0})
    await sessions.observe(runtime, stats)
    assert (
        sessions.stops[-1].next == "the simulated controller re-armed RSI after 5.7 s"
    )  # 0.5 s since the last telegram + 5.2 s
    assert sessions.report()["next"] is None and sessions.report()["running"]


async def test_no_stop_is_judged_on_an_old_report_or_while_the_controller_still_sends() -> None:
    view, stats, clock = WireView(), RsiServerStats(16), ManualClock()
    answers = [{"state": "running", "stop_cause": None, "stop_reason": None, "rearm_after_s": 5.0}]

    async def controller_status() -> dict[str, Any]:
        return answers[-1]

    sessions = RsiSessions(timeout_count=100, controller_status=controller_status, wall_clock=clock)
    runtime: Any = view
    session(view, stats, 100, 0, 0)
    await sessions.observe(runtime, stats)
    view.alive = False  # no telegram in the daemon's view...
    await sessions.observe(runtime, stats, report_age_s=0.6)  # ...because the real-time process is frozen
    await sessions.observe(runtime, stats, report_age_s=None)
    assert sessions.running and not sessions.stops
    await sessions.observe(runtime, stats)  # reports current, but the controller still sends
    assert sessions.running and not sessions.stops
    answers.append(
        {
            "state": "stopped",
            "stop_cause": "late_replies",
            "stop_reason": "Timeout: 100 late replies (limit 100)",
            "rearm_after_s": 5.0,
        }
    )
    await sessions.observe(runtime, stats)
    (stop,) = sessions.stops
    assert stop.cause == "late_replies" and stop.late_replies == 100 and not sessions.running
