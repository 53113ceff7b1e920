"""RSI server adapter over real loopback UDP, with plain sockets playing the controller."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from typing import Any

import numpy as np
import pytest

from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, build_rob, parse_sen
from comp_daemon.rt.rsi_server import RsiServerConfig, RsiServerProtocol, SampleStats, start_rsi_server

AK = (0.001, -0.002, 0.0, 0.0, 0.0, 0.0)


def step(t: RobTelegram) -> SenReply:
    return SenReply(t.ipoc, AK)


def telegram(ipoc: int, delay: int = 0) -> bytes:
    return build_rob(
        ipoc, (0.0, -90.0, 90.0, 0.0, 90.0, 0.0), (0.0, -90.0, 90.0, 0.0, 90.0, 0.0), delay=delay
    )


@pytest.fixture
def controller_sock() -> Iterator[socket.socket]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    yield s
    s.close()


Server = tuple[asyncio.DatagramTransport, RsiServerProtocol, tuple[str, int]]
MakeServer = Callable[..., Awaitable[Server]]


@pytest.fixture
async def make_server() -> AsyncIterator[MakeServer]:
    made: list[asyncio.DatagramTransport] = []

    async def make(handler: Callable[[RobTelegram], SenReply] = step, **settings: Any) -> Server:
        config = RsiServerConfig(
            **{"controller_host": "127.0.0.1", "bind_host": "127.0.0.1", "bind_port": 0, **settings}
        )
        transport, protocol = await start_rsi_server(handler, config)
        made.append(transport)
        return transport, protocol, transport.get_extra_info("sockname")[:2]

    yield make
    for t in made:
        t.close()
    await asyncio.sleep(0)


async def recv(sock: socket.socket, timeout: float = 1.0) -> bytes:
    loop = asyncio.get_running_loop()
    data, _ = await asyncio.wait_for(loop.sock_recvfrom(sock, 4096), timeout)
    return data


async def nothing_arrives(sock: socket.socket, wait_s: float = 0.15) -> bool:
    try:
        await recv(sock, wait_s)
    except TimeoutError:
        return True
    return False


async def test_reply_echoes_ipoc_with_handler_correction(
    make_server: MakeServer, controller_sock: socket.socket
) -> None:
    _, proto, addr = await make_server()
    controller_sock.sendto(telegram(5490270, delay=2), addr)
    reply = parse_sen(await recv(controller_sock))
    assert reply == SenReply(5490270, AK, False, "ImFree")
    s = proto.stats
    assert (s.received, s.answered, s.garbled, s.foreign, s.superseded) == (1, 1, 0, 0, 0)
    assert s.controller_delay == 2
    assert s.latency.count == 1 and s.latency.max is not None and s.latency.max > 0


async def test_foreign_port_and_foreign_host_are_never_answered(
    make_server: MakeServer, controller_sock: socket.socket
) -> None:
    _, proto, addr = await make_server(controller_port=controller_sock.getsockname()[1])
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other_host = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        other.bind(("127.0.0.1", 0))
        other.setblocking(False)
        other_host.bind(("127.0.0.2", 0))
        other_host.setblocking(False)
        other.sendto(telegram(12), addr)
        other_host.sendto(telegram(12), addr)
        assert await nothing_arrives(other)
        assert await nothing_arrives(other_host, 0.01)
        assert proto.stats.foreign == 2 and proto.stats.answered == 0
        controller_sock.sendto(telegram(24), addr)
        assert parse_sen(await recv(controller_sock)).ipoc == 24
    finally:
        other.close()
        other_host.close()


async def test_only_the_newest_of_queued_telegrams_is_answered(
    make_server: MakeServer, controller_sock: socket.socket
) -> None:
    seen: list[int] = []

    def handler(t: RobTelegram) -> SenReply:
        seen.append(t.ipoc)
        return SenReply(t.ipoc, AK)

    _, proto, addr = await make_server(handler)
    for ipoc in (12, 24, 36):  # queued before the loop can run: no await in between
        controller_sock.sendto(telegram(ipoc), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 36
    assert await nothing_arrives(controller_sock)
    assert seen == [36]
    assert (proto.stats.received, proto.stats.answered, proto.stats.superseded) == (3, 1, 2)


async def test_garbled_telegram_is_counted_not_answered(
    make_server: MakeServer, controller_sock: socket.socket
) -> None:
    _, proto, addr = await make_server()
    controller_sock.sendto(b"<Rob><IPOC>12</IPOC>", addr)
    assert await nothing_arrives(controller_sock)
    assert proto.stats.garbled == 1 and proto.stats.answered == 0
    controller_sock.sendto(telegram(24), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 24


@pytest.mark.parametrize("bug", ["raises", "wrong_ipoc", "nan"])
async def test_handler_bug_answers_zero_correction_and_stop(
    make_server: MakeServer, controller_sock: socket.socket, bug: str
) -> None:
    def handler(t: RobTelegram) -> SenReply:
        if bug == "raises":
            raise ZeroDivisionError("controller bug")
        if bug == "wrong_ipoc":
            return SenReply(t.ipoc - 12, AK)
        return SenReply(t.ipoc, (float("nan"),) * 6)

    _, proto, addr = await make_server(handler)
    controller_sock.sendto(telegram(120), addr)
    reply = parse_sen(await recv(controller_sock))
    assert reply == SenReply(120, (0.0,) * 6, True, "ImFree")
    assert proto.stats.handler_errors == 1


async def test_latency_jitter_late_and_skipped_cycles_with_injected_clock(
    controller_sock: socket.socket,
) -> None:
    # Clock readings: (rx, tx) per answered telegram, in ns.
    readings = iter([0, 100_000, 12_500_000, 12_600_000, 36_000_000, 56_000_000])
    config = RsiServerConfig("127.0.0.1", bind_host="127.0.0.1", bind_port=0, cycle_ms=12.0)
    transport, proto = await start_rsi_server(step, config, clock=lambda: next(readings))
    addr = transport.get_extra_info("sockname")[:2]
    try:
        for ipoc in (12, 24, 48):  # 36 is missing: one skipped cycle
            controller_sock.sendto(telegram(ipoc), addr)
            await recv(controller_sock)
        s = proto.stats
        assert list(s.latency.recent()) == [100_000, 100_000, 20_000_000]
        assert s.late == 1  # 20 ms > cycle_ms
        assert list(s.jitter.recent()) == [500_000, -500_000]  # 12.5 ms for 12; 23.5 ms for 24
        assert s.ipoc_skipped == 1
        snap = s.snapshot()
        assert snap["answered"] == 3 and snap["latency"]["max_ns"] == 20_000_000
        assert snap["latency"]["histogram_le_ns"]["100000"] == 2
    finally:
        transport.close()


def test_sample_stats_ring_keeps_the_latest_values() -> None:
    st = SampleStats(size=4)
    for v in range(10):
        st.record(v * 1000)
    assert list(st.recent()) == [6000, 7000, 8000, 9000]
    assert st.count == 10 and st.min == 0 and st.max == 9000 and st.sum == 45000
    assert st.percentiles((50.0,)) == {"p50": float(np.median([6000, 7000, 8000, 9000]))}
    assert sum(st.histogram) == 10


async def test_garbage_behind_a_valid_telegram_does_not_displace_it(
    make_server: MakeServer, controller_sock: socket.socket
) -> None:
    seen: list[int] = []

    def handler(t: RobTelegram) -> SenReply:
        seen.append(t.ipoc)
        return SenReply(t.ipoc, AK)

    _, proto, addr = await make_server(handler)
    huge_ipoc = b"<Rob><IPOC>" + b"9" * 5000 + b"</IPOC></Rob>"
    for datagram in (telegram(12), telegram(24), b"\x00garbage", huge_ipoc, b"<Rob>"):
        controller_sock.sendto(datagram, addr)  # all queued before the loop runs
    assert parse_sen(await recv(controller_sock)).ipoc == 24
    assert await nothing_arrives(controller_sock)
    assert seen == [24]
    stats = proto.stats
    assert (stats.received, stats.answered, stats.superseded, stats.garbled) == (5, 1, 1, 3)


async def test_a_telegram_behind_a_burst_of_garbage_is_not_dropped_by_the_kernel(
    make_server: MakeServer, controller_sock: socket.socket
) -> None:
    """While the process is not scheduled (here: before the loop runs again), 600 KB of garbage
    from the controller's address queue up, then a telegram: the socket's receive buffer keeps
    them all (with the system's default of 208 KiB the kernel kept 25 and dropped the rest, and
    anything arriving while it was full), every one is counted and the telegram answered."""
    _, proto, addr = await make_server()
    junk = b"<Rob><IPOC>" + b"7" * 5000 + b"</IPOC></Rob>"
    for _ in range(120):
        controller_sock.sendto(junk, addr)
    controller_sock.sendto(telegram(36), addr)
    assert parse_sen(await recv(controller_sock)).ipoc == 36
    assert (proto.stats.garbled, proto.stats.answered) == (120, 1)


class _StillPlant:
    """The robot standing still at one pose; actual = setpoint + correction."""

    def __init__(self) -> None:
        self.setpoint = np.array((0.0, -90.0, 90.0, 0.0, 45.0, 0.0))
        self.correction = np.zeros(6)

    def advance(self, dt_s: float) -> None:
        pass

    def axis_setpoint_deg(self) -> np.ndarray:
        return self.setpoint.copy()

    def axis_actual_deg(self) -> np.ndarray:
        return self.setpoint + self.correction

    def apply_correction(self, correction_deg: np.ndarray) -> None:
        self.correction = np.array(correction_deg, dtype=float)

    def start_move(self, target_axes_deg: np.ndarray) -> None:
        self.setpoint = np.array(target_axes_deg, dtype=float)

    def in_motion(self) -> bool:
        return False

    def halt(self) -> None:
        pass


_FLOODER = """
import os, socket, sys, time
port, rate, seconds, burst = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
garbage = [
    os.urandom(200),
    b"<Rob><IPOC>" + b"7" * 5000 + b"</IPOC></Rob>",
    b'<Rob Type="KUKA"><AIPos A1="x"/><IPOC>1</IPOC></Rob>',
    b"<Rob><IPOC>12</IPOC>",
    b"",
]
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
sent, t0 = 0, time.perf_counter()
while (now := time.perf_counter() - t0) < seconds:
    if sent < now * rate:
        for _ in range(burst):
            s.sendto(garbage[sent % len(garbage)], ("127.0.0.1", port))
            sent += 1
    time.sleep(0.0002)
print(sent)
"""


async def test_garbage_flood_from_the_controller_address_misses_no_valid_telegram(
    make_server: MakeServer,
) -> None:
    """A second process floods garbage from the controller's host (2 000 datagrams/s in bursts of 20)
    while the simulated controller runs its 12 ms cycle and the loop has other work: every telegram
    the controller sends is answered or, after a machine stall, superseded by a newer valid one; RSI
    keeps running. (Keeping the newest datagram instead of the newest telegram answered about half
    and the controller stopped on "10 late replies".)"""
    import sys
    import time

    from comp_daemon.sim.rsi_controller import RsiControllerConfig, RsiState, SimulatedRsiController

    answered: list[int] = []

    def handler(t: RobTelegram) -> SenReply:
        answered.append(t.ipoc)
        return SenReply(t.ipoc, AK if len(answered) % 2 else tuple(-v for v in AK))

    _, proto, addr = await make_server(handler)
    controller = SimulatedRsiController(
        RsiControllerConfig(server_host=addr[0], server_port=addr[1], cycle_ms=12), _StillPlant()
    )
    flood_s, rate = 3.0, 2000.0
    flooder = await asyncio.create_subprocess_exec(
        sys.executable, "-c", _FLOODER, str(addr[1]), str(rate), str(flood_s), "20",
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip

    async def other_work() -> None:  # the loop's other duties (gratings, telemetry): busy 2 ms in 5
        while True:
            time.sleep(0.002)
            await asyncio.sleep(0.003)

    await controller.start()
    busy = asyncio.create_task(other_work())
    try:
        out, _ = await asyncio.wait_for(flooder.communicate(), flood_s + 30)
    finally:
        busy.cancel()
        await controller.close()
    await asyncio.sleep(0.1)  # the server takes the last telegram sent
    flood = int(out)
    stats, sent = proto.stats, controller.stats.telegrams_sent
    assert controller.state is RsiState.STOPPED and controller.stop_reason == "controller shut down"
    assert flood > 0.8 * rate * flood_s and stats.garbled >= flood - 10  # the flood arrived, all refused
    assert stats.answered + stats.superseded == sent  # no valid telegram lost to garbage
    assert answered == sorted(set(answered))  # each answered once, in order
    # late only behind a machine stall, if at all (then a telegram waits, or the controller's cycle
    # is itself late and judges before the reply is read)
    assert controller.stats.late_total <= stats.superseded + controller.stats.overruns + 1
    assert stats.superseded <= 0.1 * sent, stats.snapshot()
