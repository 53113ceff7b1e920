"""Simulated RSI controller against the daemon's RSI server (and misbehaving servers), real loopback UDP."""

from __future__ import annotations

import asyncio
import json
import socket
import statistics
import threading
import time
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any

import numpy as np
import pytest

from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, build_sen, parse_rob
from comp_daemon.rt.rsi_server import RsiServerConfig, RsiServerProtocol, start_rsi_server
from comp_daemon.sim.rsi_controller import (
    RobotStoppedError,
    RsiControllerConfig,
    RsiState,
    SimulatedRsiController,
)

HOME = (0.0, -90.0, 90.0, 0.0, 45.0, 0.0)
ZERO = (0.0,) * 6


class RigidPlant:
    """In-test joint source: the setpoint moves at a constant axis speed; actual = setpoint + correction."""

    def __init__(self, start: Sequence[float] = HOME, speed_deg_s: float = 90.0) -> None:
        self.setpoint = np.array(start, dtype=float)
        self.correction = np.zeros(6)
        self.target: np.ndarray | None = None
        self.speed_deg_s = speed_deg_s
        self.halts = 0
        self.elapsed_s = 0.0

    def advance(self, dt_s: float) -> None:
        self.elapsed_s += dt_s
        if self.target is not None:
            self.setpoint += np.clip(
                self.target - self.setpoint, -self.speed_deg_s * dt_s, self.speed_deg_s * dt_s
            )
            if np.array_equal(self.setpoint, self.target):
                self.target = None

    def axis_setpoint_deg(self) -> np.ndarray:
        return self.setpoint.copy()

    def axis_actual_deg(self) -> np.ndarray:
        return self.setpoint + self.correction

    def apply_correction(self, correction_deg: np.ndarray) -> None:
        self.correction = np.array(correction_deg, dtype=float)

    def start_move(self, target_axes_deg: np.ndarray) -> None:
        self.target = np.array(target_axes_deg, dtype=float)

    def in_motion(self) -> bool:
        return self.target is not None

    def halt(self) -> None:
        self.target = None
        self.halts += 1


async def until(cond: Callable[[], bool], timeout_s: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not cond():
        if loop.time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.005)


async def without_stalls(run: Callable[[], Any], clean: Callable[[Any], bool], attempts: int = 5) -> Any:
    """Run a cycle-exact scenario until one run had no reply delayed by a machine stall (> 1 cycle).

    On a shared, loaded machine the event loop is sometimes descheduled for longer than a cycle; the
    controller then rightly counts a late reply, which changes the exact sequence the test checks.
    """
    for _ in range(attempts):
        result = await run()
        if clean(result):
            return result
    pytest.fail(f"every one of {attempts} runs had a reply delayed by more than a cycle")


class Recorder:
    """A daemon-side controller step that records what it saw and answers from a rule."""

    def __init__(self, rule: Callable[[int, RobTelegram], SenReply | None] | None = None) -> None:
        self.telegrams: list[RobTelegram] = []
        self.arrivals_ns: list[int] = []
        self.rule = rule

    def __call__(self, t: RobTelegram) -> SenReply:
        self.telegrams.append(t)
        self.arrivals_ns.append(time.perf_counter_ns())
        reply = self.rule(len(self.telegrams), t) if self.rule else None
        return reply if reply is not None else SenReply(t.ipoc, ZERO)

    def aipos(self, ipoc: int) -> tuple[float, ...]:
        for t in self.telegrams:
            if t.ipoc == ipoc:
                assert t.aipos_deg is not None
                return t.aipos_deg
        raise KeyError(ipoc)


class RawServer(asyncio.DatagramProtocol):
    """A misbehaving daemon: ``answer(n, telegram) -> bytes | None`` decides each reply."""

    def __init__(self, answer: Callable[[int, RobTelegram], bytes | None]) -> None:
        self.answer = answer
        self.telegrams: list[RobTelegram] = []
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        t = parse_rob(data)
        self.telegrams.append(t)
        out = self.answer(len(self.telegrams), t)
        if out is not None and self.transport is not None:
            self.transport.sendto(out, addr)


Cell = Callable[..., Any]


@pytest.fixture
async def cell() -> AsyncIterator[Cell]:
    """Factory: daemon RSI server (or a raw misbehaving one) + simulated controller on a rigid plant."""
    closers: list[Callable[[], Any]] = []

    async def make(
        handler: Callable[[RobTelegram], SenReply] | None = None,
        raw: RawServer | None = None,
        plant: RigidPlant | None = None,
        **controller_cfg: Any,
    ) -> tuple[SimulatedRsiController, Any, RigidPlant]:
        loop = asyncio.get_running_loop()
        if raw is not None:
            transport, server = await loop.create_datagram_endpoint(
                lambda: raw, local_addr=("127.0.0.1", 0), family=socket.AF_INET
            )
        else:
            config = RsiServerConfig("127.0.0.1", bind_host="127.0.0.1", bind_port=0)
            transport, server = await start_rsi_server(handler or Recorder(), config)
        closers.append(transport.close)
        port = transport.get_extra_info("sockname")[1]
        plant = plant or RigidPlant()
        controller = SimulatedRsiController(RsiControllerConfig(server_port=port, **controller_cfg), plant)
        await controller.start()
        closers.append(controller.close)
        return controller, server, plant

    yield make
    for close in reversed(closers):
        result = close()
        if asyncio.iscoroutine(result):
            await result
    await asyncio.sleep(0)


@pytest.mark.parametrize("cycle_ms", [12, 4])
async def test_ipoc_grows_by_the_cycle_and_telegrams_keep_time(cell: Cell, cycle_ms: int) -> None:
    rec = Recorder()
    controller, server, _ = await cell(rec, cycle_ms=cycle_ms, timeout_count=100)
    await until(lambda: len(rec.telegrams) >= 60)
    ipocs = [t.ipoc for t in rec.telegrams]
    assert ipocs[0] == 1_000_000
    gaps = np.diff(ipocs)
    # Every step is one cycle, or whole cycles when the loop woke up late (never anything else).
    assert np.all(gaps % cycle_ms == 0) and np.all(gaps > 0) and np.mean(gaps == cycle_ms) > 0.5
    periods_ms = np.diff(rec.arrivals_ns)[gaps == cycle_ms] / 1e6
    assert abs(statistics.median(periods_ms) - cycle_ms) < 2.0
    # Drift-free: IPOC (the schedule) and the wall clock agree over the whole run.
    span_ms = (rec.arrivals_ns[-1] - rec.arrivals_ns[0]) / 1e6
    assert abs(span_ms - (ipocs[-1] - ipocs[0])) < 3 * cycle_ms + 5.0
    assert controller.state is RsiState.RUNNING
    assert isinstance(server, RsiServerProtocol) and server.stats.answered >= 60
    assert all(t.aipos_deg == HOME and t.aspos_deg == HOME and t.rob_type == "KUKA" for t in rec.telegrams)


@pytest.mark.parametrize("lag", [0, 1, 2])
async def test_correction_shows_in_aipos_after_the_servo_lag(cell: Cell, lag: int) -> None:
    step_at = 5  # the 5th reply carries AK A1 = +0.01, A3 = -0.02

    def rule(n: int, t: RobTelegram) -> SenReply | None:
        return SenReply(t.ipoc, (0.01, 0.0, -0.02, 0.0, 0.0, 0.0)) if n == step_at else None

    async def run() -> tuple[Recorder, SimulatedRsiController]:
        rec = Recorder(rule)
        controller, _, _ = await cell(rec, servo_lag_cycles=lag)
        await until(lambda: len(rec.telegrams) >= step_at + lag + 4)
        return rec, controller

    def clean(r: tuple[Recorder, SimulatedRsiController]) -> bool:
        return r[1].stats.late_total == 0 and bool(np.all(np.diff([t.ipoc for t in r[0].telegrams]) == 12))

    rec, controller = await without_stalls(run, clean)
    j = rec.telegrams[step_at - 1].ipoc
    first = j + (1 + lag) * 12
    before = rec.aipos(first - 12)
    after = rec.aipos(first)
    assert before == HOME
    assert after == pytest.approx((0.01, -90.0, 89.98, 0.0, 45.0, 0.0), abs=1e-9)
    assert rec.aipos(first + 24) == after  # relative mode: zero steps hold the correction
    assert rec.telegrams[-1].aspos_deg == HOME  # setpoint without corrections
    np.testing.assert_allclose(controller.total_correction_deg, [0.01, 0, -0.02, 0, 0, 0])


@pytest.mark.parametrize("mismatch", [False, True], ids=["silent", "wrong-ipoc"])
async def test_rsi_stops_after_timeout_late_replies(cell: Cell, mismatch: bool) -> None:
    def answer(n: int, t: RobTelegram) -> bytes | None:
        if n <= 5:
            return build_sen(SenReply(t.ipoc))
        return build_sen(SenReply(t.ipoc - 12)) if mismatch else None

    async def run() -> tuple[RawServer, SimulatedRsiController, RigidPlant, asyncio.Future[None]]:
        raw = RawServer(answer)
        controller, _, plant = await cell(raw=raw)
        moving = asyncio.ensure_future(controller.move_to((90.0, -80.0, 90.0, 0.0, 45.0, 0.0)))
        await until(lambda: controller.state is RsiState.STOPPED)
        if raw.telegrams[5].delay != 0:  # a stall made one of the first five replies late
            moving.cancel()
        return raw, controller, plant, moving

    raw, controller, plant, moving = await without_stalls(run, lambda r: r[0].telegrams[5].delay == 0)
    assert controller.stop_reason is not None and controller.stop_reason.startswith("Timeout: 10 late")
    assert controller.stats.telegrams_sent == 15  # 5 answered, 10 late, then no more
    assert [t.delay for t in raw.telegrams] == [0] * 6 + list(range(1, 10))
    assert controller.stats.mismatched == (10 if mismatch else 0)
    assert plant.halts == 1
    with pytest.raises(RobotStoppedError, match="Timeout"):
        await moving
    await asyncio.sleep(0.05)
    assert len(raw.telegrams) == 15  # silence after the stop


@pytest.mark.parametrize("holdon", [True, False])
async def test_holdon_repeats_the_last_correction_while_a_reply_is_late(cell: Cell, holdon: bool) -> None:
    def answer(n: int, t: RobTelegram) -> bytes | None:
        if n in (4, 5):
            return None  # two late replies
        ak = (0.001, 0.0, 0.0, 0.0, 0.0, 0.0) if n <= 3 else ZERO
        return build_sen(SenReply(t.ipoc, ak))

    async def run() -> SimulatedRsiController:
        controller, _, _ = await cell(raw=RawServer(answer), holdon=holdon)
        await until(lambda: controller.stats.telegrams_sent >= 10)
        return controller

    controller = await without_stalls(run, lambda c: c.stats.late == 2 and c.stats.mismatched == 0)
    assert controller.state is RsiState.RUNNING
    expected = 0.005 if holdon else 0.003
    assert controller.total_correction_deg[0] == pytest.approx(expected, abs=1e-12)


async def test_axiscorr_clips_the_total_correction(cell: Cell) -> None:
    rec = Recorder(lambda n, t: SenReply(t.ipoc, (0.1, -0.1, 0.0, 0.0, 0.0, 0.0)))
    controller, _, _ = await cell(rec, axiscorr_min_deg=-0.25, axiscorr_max_deg=(0.25, 0.25, 1, 1, 1, 1))
    await until(lambda: len(rec.telegrams) >= 8)
    np.testing.assert_allclose(controller.total_correction_deg[:2], [0.25, -0.25])
    assert controller.stats.axiscorr_limited >= 1 and controller.state is RsiState.RUNNING
    assert max(t.aipos_deg[0] for t in rec.telegrams if t.aipos_deg) == pytest.approx(0.25)  # type: ignore[index]


async def test_axiscorrmon_stops_rsi(cell: Cell) -> None:
    async def run() -> tuple[Recorder, SimulatedRsiController, RigidPlant]:
        rec = Recorder(lambda n, t: SenReply(t.ipoc, (0.0, 0.0, 0.0, 0.0, 0.0, 0.1)))
        controller, _, plant = await cell(rec, axiscorrmon_max_deg=0.25)
        await until(lambda: controller.state is RsiState.STOPPED)
        return rec, controller, plant

    rec, controller, plant = await without_stalls(run, lambda r: r[1].stats.late_total == 0)
    assert (
        controller.stop_reason is not None
        and "AXISCORRMON" in controller.stop_reason
        and "A6" in controller.stop_reason
    )
    assert len(rec.telegrams) == 3  # totals 0.1, 0.2 accepted; 0.3 stops
    assert plant.halts == 1


async def test_stop_request_stops_rsi_and_motion(cell: Cell) -> None:
    asking = [True]
    rec = Recorder(lambda n, t: SenReply(t.ipoc, stop=True) if n >= 3 and asking[0] else None)
    controller, _, plant = await cell(rec, timeout_count=100)
    with pytest.raises(RobotStoppedError, match="Stop=1"):
        await controller.move_to((90.0, -90.0, 90.0, 0.0, 45.0, 0.0))
    assert controller.state is RsiState.STOPPED
    assert 0.0 < plant.setpoint[0] < 90.0  # halted on the way
    asking[0] = False
    controller.rsi_on()  # a new session starts sending again with the late count reset
    sent = controller.stats.telegrams_sent
    await until(lambda: controller.stats.telegrams_sent >= sent + 3)
    assert controller.state is RsiState.RUNNING and controller.stats.sessions == 2


async def test_move_and_command_port(cell: Cell) -> None:
    rec = Recorder()
    controller, _, plant = await cell(rec, timeout_count=100)
    await controller.move_to((3.0, -88.0, 90.0, 0.0, 45.0, 0.0))
    np.testing.assert_array_equal(plant.setpoint, [3.0, -88.0, 90.0, 0.0, 45.0, 0.0])
    await until(lambda: rec.telegrams[-1].aspos_deg == (3.0, -88.0, 90.0, 0.0, 45.0, 0.0))
    host, port = await controller.serve_commands()
    reader, writer = await asyncio.open_connection(host, port)
    try:
        writer.write(b"move 0 -90 90 0 45 1.5\nstatus\nmove 1 2\nfly\n")
        assert (await reader.readline()).strip() == b"OK arrived"
        status = json.loads((await reader.readline()).decode()[3:])
        assert status["state"] == "running" and status["axis_setpoint_deg"] == [
            0.0,
            -90.0,
            90.0,
            0.0,
            45.0,
            1.5,
        ]
        assert (await reader.readline()).startswith(b"ERR move needs 6")
        assert (await reader.readline()).startswith(b"ERR unknown command")
    finally:
        writer.close()
        await writer.wait_closed()


async def test_foreign_sender_is_ignored_while_the_controller_runs(cell: Cell) -> None:
    rec = Recorder()
    controller, server, _ = await cell(rec, timeout_count=100)
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        intruder.bind(("127.0.0.2", 0))
        port = server.transport.get_extra_info("sockname")[1]
        for ipoc in (1, 2, 3):
            intruder.sendto(b'<Rob Type="KUKA"><IPOC>%d</IPOC></Rob>' % ipoc, ("127.0.0.1", port))
        await until(lambda: len(rec.telegrams) >= 10)
        assert server.stats.foreign == 3
        assert all(t.ipoc >= 1_000_000 for t in rec.telegrams)
        intruder.setblocking(False)
        with pytest.raises(BlockingIOError):
            intruder.recv(100)
        assert controller.state is RsiState.RUNNING and controller.stats.garbled == 0
    finally:
        intruder.close()


def test_only_the_newest_telegram_is_answered_after_a_stall() -> None:
    """Controller in its own thread and loop; the daemon's loop stalls for ~5 cycles."""
    answered: list[int] = []
    ready = threading.Event()
    done = threading.Event()
    result: dict[str, Any] = {}
    port_box: list[int] = []

    async def controller_main() -> None:
        c = SimulatedRsiController(
            RsiControllerConfig(server_port=port_box[0], timeout_count=1000), RigidPlant()
        )
        await c.start()
        ready.set()
        while not done.is_set():
            await asyncio.sleep(0.01)
        result["stats"] = c.stats
        await c.close()

    async def daemon_main() -> None:
        def handler(t: RobTelegram) -> SenReply:
            answered.append(t.ipoc)
            return SenReply(t.ipoc)

        transport, proto = await start_rsi_server(
            handler, RsiServerConfig("127.0.0.1", bind_host="127.0.0.1", bind_port=0)
        )
        port_box.append(transport.get_extra_info("sockname")[1])
        thread = threading.Thread(target=asyncio.run, args=(controller_main(),))
        thread.start()
        try:
            await asyncio.get_running_loop().run_in_executor(None, ready.wait, 5.0)
            await until(lambda: len(answered) >= 5)
            time.sleep(0.062)  # the daemon's loop is blocked: ~5 telegrams queue up
            before = proto.stats.superseded
            await until(lambda: proto.stats.answered >= len(answered) and len(answered) >= 12)
            result["superseded"] = proto.stats.superseded - before
        finally:
            done.set()
            await asyncio.get_running_loop().run_in_executor(None, thread.join, 5.0)
            transport.close()

    asyncio.run(daemon_main())
    gaps = np.diff(answered)
    assert result["superseded"] >= 3  # the backlog was drained, not answered one by one
    assert gaps.max() >= 48  # one jump over the skipped telegrams …
    assert np.all(gaps > 0) and np.all(gaps % 12 == 0)  # … and never an old one answered after a newer one
    stats = result["stats"]
    assert stats.late_total >= 3  # the superseded ones were late at the controller
