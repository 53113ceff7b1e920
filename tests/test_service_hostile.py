"""The HTTP side under hostile clients, over real sockets: half-sent requests, slow bodies, too many
connections, keep-alive latency (TCP_NODELAY), the accept-error log line."""

from __future__ import annotations

import asyncio
import logging
import socket
import statistics
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import Settings, load_settings
from comp_daemon.service.http_server import AcceptErrorFilter, HttpServer, build_http_server

HALF_SENT = b"GET /health HTTP/1.1\r\nHost: cell\r\n"  # the blank line that ends the headers never comes


def make_settings(tmp_path: Path, **http: Any) -> Settings:
    return load_settings(
        None,
        store={"data_dir": str(tmp_path / "data")},
        http={"host": "127.0.0.1", "port": 0, **http},
    )


@pytest.fixture
async def serve(tmp_path: Path) -> AsyncIterator[Any]:
    """``await serve(**http_settings) -> HttpServer`` serving the app in this loop."""
    running: list[tuple[HttpServer, asyncio.Task[None]]] = []
    stores = []

    async def start(**http: Any) -> HttpServer:
        settings = make_settings(tmp_path, **http)
        store = open_store(settings)
        stores.append(store)
        server = build_http_server(create_app(settings, store), settings.http)
        task = asyncio.create_task(server.serve())
        running.append((server, task))
        for _ in range(500):
            if server.started:
                return server
            await asyncio.sleep(0.01)
        raise AssertionError("the HTTP server did not start")

    yield start
    for server, task in running:
        server.stop()
        await asyncio.wait_for(task, 10)
    for store in stores:
        store.close()


async def connect(port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.open_connection("127.0.0.1", port)


async def get(port: int, path: str = "/health", timeout: float = 2.0) -> tuple[int, float]:
    """One request on a fresh connection: (status, seconds)."""
    t0 = time.perf_counter()
    reader, writer = await connect(port)
    try:
        writer.write(f"GET {path} HTTP/1.1\r\nHost: cell\r\nConnection: close\r\n\r\n".encode())
        status_line = await asyncio.wait_for(reader.readline(), timeout)
        await asyncio.wait_for(reader.read(), timeout)
    finally:
        writer.close()
    return int(status_line.split()[1]), time.perf_counter() - t0


async def closed_within(reader: asyncio.StreamReader, timeout: float) -> bytes:
    """What the server sent before closing (raises TimeoutError if it keeps the connection open)."""
    data = b""
    async with asyncio.timeout(timeout):
        while True:
            try:
                chunk = await reader.read(4096)
            except ConnectionResetError:
                return data
            if not chunk:
                return data
            data += chunk


async def test_half_sent_requests_beyond_the_cap_leave_room_and_time_out(serve: Any) -> None:
    cap, header_timeout = 16, 1.0
    server = await serve(max_connections=cap, header_timeout_s=header_timeout)
    clients = []
    for _ in range(4 * cap):  # the attack: many connections, each a request that never completes
        reader, writer = await connect(server.port)
        writer.write(HALF_SENT)
        clients.append((reader, writer))
    await asyncio.sleep(0.2)
    connections = server.server.server_state.connections
    assert len(connections) <= cap
    status, seconds = await get(server.port)  # a fresh client is still served, at once
    assert status == 200 and seconds < 0.5
    assert server.guard.evicted >= 3 * cap
    t0 = time.perf_counter()
    answers = await asyncio.gather(*(closed_within(r, header_timeout + 2.0) for r, _ in clients))
    assert time.perf_counter() - t0 < header_timeout + 2.0  # every half-sent one is closed
    timed_out = [a for a in answers if a.startswith(b"HTTP/1.1 408")]
    assert len(timed_out) == server.guard.header_timeouts >= 1  # the last ones waited out their time
    assert server.guard.header_timeouts + server.guard.evicted >= 4 * cap
    for _, w in clients:
        w.close()
    await asyncio.sleep(0.05)
    assert len(connections) == 0


async def test_a_trickle_of_header_bytes_does_not_keep_a_connection(serve: Any) -> None:
    server = await serve(header_timeout_s=0.8, keep_alive_s=5)
    reader, writer = await connect(server.port)
    t0 = time.perf_counter()

    async def trickle() -> None:
        for byte in HALF_SENT * 10:
            writer.write(bytes([byte]))
            await asyncio.sleep(0.05)

    sender = asyncio.create_task(trickle())
    try:
        answer = await closed_within(reader, 3.0)
    finally:
        sender.cancel()
        writer.close()
    assert answer.startswith(b"HTTP/1.1 408") and 0.7 < time.perf_counter() - t0 < 2.0


async def test_a_body_that_never_completes_is_closed_after_body_timeout(serve: Any) -> None:
    server = await serve(body_timeout_s=0.8, header_timeout_s=30)
    reader, writer = await connect(server.port)
    writer.write(
        b"POST /api/datasets HTTP/1.1\r\nHost: cell\r\nContent-Type: text/csv\r\n"
        b"Content-Length: 100000\r\n\r\na1,a2"
    )
    t0 = time.perf_counter()
    await closed_within(reader, 3.0)
    writer.close()
    assert 0.7 < time.perf_counter() - t0 < 2.5 and server.guard.body_timeouts == 1


async def test_when_every_connection_is_busy_a_new_one_is_answered_503(serve: Any) -> None:
    server = await serve(max_connections=3, body_timeout_s=30, header_timeout_s=30)
    busy = []
    for _ in range(3):  # three uploads whose bodies are still coming: not to be dropped for others
        reader, writer = await connect(server.port)
        writer.write(
            b"POST /api/datasets HTTP/1.1\r\nHost: cell\r\nContent-Type: text/csv\r\n"
            b"Content-Length: 100000\r\n\r\na1"
        )
        busy.append((reader, writer))
    await asyncio.sleep(0.2)
    reader, writer = await connect(server.port)
    answer = await closed_within(reader, 2.0)
    writer.close()
    assert answer.startswith(b"HTTP/1.1 503") and b"retry-after: 1" in answer
    assert server.guard.refused == 1 and server.guard.evicted == 0
    for r, w in busy:
        assert not r.at_eof()
        w.close()


async def test_keep_alive_requests_are_not_held_by_nagle(serve: Any) -> None:
    server = await serve()
    reader, writer = await connect(server.port)
    times = []
    try:
        for _ in range(15):
            t0 = time.perf_counter()
            writer.write(b"GET /health HTTP/1.1\r\nHost: cell\r\n\r\n")
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 2)
            length = int(
                next(h for h in head.split(b"\r\n") if h.lower().startswith(b"content-length")).split(b":")[1]
            )
            await reader.readexactly(length)
            times.append(time.perf_counter() - t0)
        (conn,) = server.server.server_state.connections
        sock = conn.transport.get_extra_info("socket")
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
    finally:
        writer.close()
    assert statistics.median(times) < 0.02, times  # a delayed ACK would add ~40 ms to each


def test_accept_error_is_logged_once_per_interval_with_the_count_held_back() -> None:
    flt = AcceptErrorFilter(interval_s=0.2)
    logger = logging.getLogger("test.hostile.accept")
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Keep()
    logger.addHandler(handler)
    logger.addFilter(flt)
    logger.propagate = False
    try:
        for _ in range(3000):
            logger.error("socket.accept() out of system resource\nsocket: <socket>")
        logger.error("something else")
        time.sleep(0.25)
        logger.error("socket.accept() out of system resource\nsocket: <socket>")
    finally:
        logger.removeHandler(handler)
        logger.removeFilter(flt)
    messages = [r.getMessage() for r in records]
    assert len(messages) == 3 and messages[1] == "something else"
    assert "(2999 more held back in the last 0.2 s)" in messages[2].splitlines()[0]


_SERVER_WITH_FEW_FILES = """
import asyncio, resource, sys
resource.setrlimit(resource.RLIMIT_NOFILE, (160, 160))
from comp_daemon.common.logs import configure_logging
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import load_settings
from comp_daemon.service.http_server import build_http_server

async def main():
    configure_logging("INFO", "console")
    settings = load_settings(None, store={"data_dir": sys.argv[1]},
                             http={"port": 0, "max_connections": 64, "header_timeout_s": 2.0})
    store = open_store(settings)
    server = build_http_server(create_app(settings, store), settings.http)
    print(server.port, flush=True)
    await server.serve()

asyncio.run(main())
"""


async def test_a_process_with_few_file_descriptors_outlasts_a_connection_flood(tmp_path: Path) -> None:
    """The server process may open 160 files; 600 half-sent requests arrive. It never runs out of
    descriptors (no accept error), answers a fresh request at once, and closes the flood."""
    import os
    import sys

    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", _SERVER_WITH_FEW_FILES, str(tmp_path / "data"),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env={**os.environ},
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    try:
        port = int(await asyncio.wait_for(proc.stdout.readline(), 60))
        clients = []
        for _ in range(600):
            reader, writer = await connect(port)
            writer.write(HALF_SENT)
            clients.append((reader, writer))
        statuses = [await get(port) for _ in range(5)]
        assert all(status == 200 and seconds < 1.0 for status, seconds in statuses), statuses
        answers = await asyncio.gather(*(closed_within(r, 6.0) for r, _ in clients))
        assert sum(a.startswith(b"HTTP/1.1 408") for a in answers) >= 1
        for _, w in clients:
            w.close()
        assert (await get(port))[0] == 200
    finally:
        proc.terminate()
        _, err = await asyncio.wait_for(proc.communicate(), 30)
    log = err.decode(errors="replace")
    assert "out of system resource" not in log and "Too many open files" not in log, log[-2000:]
    assert "http connections closed by the guard" in log
