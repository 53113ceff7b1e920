"""The real-time process's per-cycle trace (comp_daemon.rt.cycle_trace) on a real UDP endpoint.

What is checked: each answered telegram gets a row with the kernel's receive time before the
callback's entry and the reply after it; a telegram that waited in the socket while the loop was
busy shows the wait and the CPU time the loop spent meanwhile; a collector pass between two
telegrams is timed with its generation; two telegrams queued together are one row with two taken;
the ring keeps the newest rows; the file written at exit reads back; a bad setting is named.
"""

from __future__ import annotations

import asyncio
import gc
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.rt.cycle_trace import COLUMNS, CycleTrace, from_environment
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, build_rob, parse_sen
from comp_daemon.rt.rsi_server import RsiServerConfig, start_rsi_server

AXES = (0.0, -90.0, 90.0, 0.0, 0.0, 0.0)


def _handler(t: RobTelegram) -> SenReply:
    return SenReply(t.ipoc, (0.0,) * 6, False, "ImFree")


async def _exchange(sock: socket.socket, address: tuple[str, int], ipoc: int) -> int:
    sock.sendto(build_rob(ipoc, AXES, AXES), address)
    loop = asyncio.get_running_loop()
    data = await asyncio.wait_for(loop.sock_recv(sock, 65536), 2.0)
    return parse_sen(data).ipoc


async def test_each_reply_gets_a_row_that_says_what_held_it(tmp_path: Path) -> None:
    trace = CycleTrace(tmp_path / "trace.npz", capacity=8)
    transport, proto = await start_rsi_server(
        _handler, RsiServerConfig(controller_host="127.0.0.1", bind_port=0), trace=trace
    )
    address = transport.get_extra_info("sockname")[:2]
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.bind(("127.0.0.1", 0))
    client.setblocking(False)
    try:
        assert await _exchange(client, address, 100) == 100
        # the loop is busy (CPU) for 30 ms while the next telegram waits in the socket
        client.sendto(build_rob(104, AXES, AXES), address)
        end = time.thread_time() + 0.03
        while time.thread_time() < end:
            pass
        assert (
            parse_sen(await asyncio.wait_for(asyncio.get_running_loop().sock_recv(client, 65536), 2)).ipoc
            == 104
        )
        gc.collect()  # a full collector pass before the next telegram
        assert await _exchange(client, address, 108) == 108
        # two telegrams queued while the loop is blocked: one row, two taken, the newer answered
        client.sendto(build_rob(112, AXES, AXES), address)
        client.sendto(build_rob(116, AXES, AXES), address)
        time.sleep(0.02)
        assert (
            parse_sen(await asyncio.wait_for(asyncio.get_running_loop().sock_recv(client, 65536), 2)).ipoc
            == 116
        )
    finally:
        client.close()
        transport.close()
        trace.close()
    t = trace.table()
    assert list(t["ipoc"]) == [100, 104, 108, 116] and list(t["seq"]) == [0, 1, 2, 3]
    assert np.all(t["kernel_first_ns"] > 0) and np.all(t["kernel_first_ns"] <= t["entry_ns"])
    assert np.all(t["entry_ns"] <= t["sent_ns"]) and np.all(t["kernel_last_ns"] >= t["kernel_first_ns"])
    busy = 1  # the 30 ms of CPU: the telegram waited that long, and the loop's CPU time shows why
    assert t["entry_ns"][busy] - t["kernel_first_ns"][busy] > 25e6
    assert t["cpu_ns"][busy] > 25e6 and t["gc_gen"][busy] == -1
    assert t["gc_gen"][2] == 2 and t["gc_ns"][2] > 0
    assert list(t["taken"]) == [1, 1, 1, 2] and proto.stats.superseded == 1
    assert t["kernel_last_ns"][3] > t["kernel_first_ns"][3]  # the newer of the two came later
    trace.write()
    with np.load(tmp_path / "trace.npz") as z:
        assert sorted(z.files) == sorted(COLUMNS) and list(z["ipoc"]) == [100, 104, 108, 116]


def test_the_ring_keeps_the_newest_rows(tmp_path: Path) -> None:
    trace = CycleTrace(tmp_path / "t.npz", capacity=3)
    for ipoc in range(10, 15):
        trace.record(ipoc, 1, 1, trace.entry(), 1)
    t = trace.table()
    assert list(t["ipoc"]) == [12, 13, 14] and list(t["seq"]) == [2, 3, 4]


def test_the_environment_turns_it_on_and_a_bad_size_is_named(tmp_path: Path) -> None:
    assert from_environment({}) is None
    trace = from_environment(
        {"COMP_DAEMON_RT_TRACE": str(tmp_path / "t.npz"), "COMP_DAEMON_RT_TRACE_CYCLES": "5"}
    )
    assert trace is not None and trace.capacity == 5
    with pytest.raises(
        ValueError, match="COMP_DAEMON_RT_TRACE_CYCLES must be a whole number of cycles, not 'many'"
    ):
        from_environment({"COMP_DAEMON_RT_TRACE": "x.npz", "COMP_DAEMON_RT_TRACE_CYCLES": "many"})
    with pytest.raises(ValueError, match="COMP_DAEMON_RT_TRACE_CYCLES must be at least 1"):
        from_environment({"COMP_DAEMON_RT_TRACE": "x.npz", "COMP_DAEMON_RT_TRACE_CYCLES": "0"})
