"""The simulated controller re-arms RSI after a stop, as an operator restarting the program would.

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

from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, build_sen
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
    replying = False

    def answer(n: int, t: RobTelegram) -> bytes | None:
        return ok(n, t) if replying else None

    controller, _ = await make(answer, clock, timeout_count=2, rearm_after_s=1.0)
    await until(lambda: controller.state is RsiState.STOPPED)
    replying = True
    clock.t += 1.0
    await until(lambda: controller.stats.sessions == 2)
    before = controller.stats.replies_ok
    await until(lambda: controller.stats.replies_ok >= before + 50)
    assert controller.state is RsiState.RUNNING and controller.stop_reason is None


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
        return build_sen(SenReply(t.ipoc, stop=n == 4))

    controller, _ = await make(answer, clock, rearm_after_s=2.0)
    await until(lambda: controller.state is RsiState.STOPPED)
    (stop,) = controller.stats.stops
    assert stop.cause is StopCause.SENSOR_STOP and stop.late == 0 and stop.telegrams == 4
    clock.t += 2.0
    await until(lambda: controller.stats.sessions == 2)


def test_rearm_pause_must_be_finite_and_not_negative() -> None:
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="rearm_after_s"):
            RsiControllerConfig(rearm_after_s=bad)
