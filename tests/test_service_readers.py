"""Readers against a real HTTP server in this process: memory held by list pages and unread
downloads, one late-reply count and one ready rule, the status snapshot under 50 clients."""

from __future__ import annotations

import asyncio
import hashlib
import socket
import statistics
import time
import tracemalloc
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
from test_service_api import TOKENS, auth

from comp_daemon.daemon.app import Daemon
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.loop import LoopRuntime
from comp_daemon.rt.rsi_server import RsiServerStats
from comp_daemon.rt.safety import FaultKind, SafetySettings
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import Settings, load_settings
from comp_daemon.service.daemon_view import DaemonView
from comp_daemon.service.http_server import HttpServer, build_http_server
from comp_daemon.service.store import ModelDraft, Store

MB = 1 << 20


def make_settings(tmp_path: Path, **http: Any) -> Settings:
    return load_settings(
        None,
        store={"data_dir": str(tmp_path / "data")},
        http={"host": "127.0.0.1", "port": 0, **http},
        auth={"tokens": [{"name": f"{r}-1", "role": r, "token": t} for r, t in TOKENS.items()]},
    )


def csv_text(size: int, seed: int) -> str:
    """A CSV of about ``size`` bytes (the store keeps what it is given; these tests read it back)."""
    line = f"{seed},0.1,0.2,0.3,0.4,0.5,0.6,1.5,2.5,3.5\n"
    return "n,a1,a2,a3,a4,a5,a6,x,y,z\n" + line * (size // len(line))


def add_dataset(store: Store, content: str, name: str) -> int:
    digest = hashlib.sha256(content.encode()).hexdigest()
    return store.add_dataset(
        name=name, format="csv", content=content, sha256=digest, rows=content.count("\n") - 1, summary={}
    ).id


Serve = Callable[..., Any]


@pytest.fixture
async def serve(tmp_path: Path) -> AsyncIterator[Serve]:
    """``await serve(daemon_view=None, **http) -> (HttpServer, Store, base URL)`` in this loop."""
    running: list[tuple[HttpServer, asyncio.Task[None], Any]] = []

    async def start(daemon_view: DaemonView | None = None, **http: Any) -> tuple[HttpServer, Store, str]:
        settings = make_settings(tmp_path, **http)
        store = open_store(settings)
        server = build_http_server(create_app(settings, store, daemon_view), settings.http)
        task = asyncio.create_task(server.serve())
        running.append((server, task, store))
        for _ in range(500):
            if server.started:
                return server, store, f"http://127.0.0.1:{server.port}"
            await asyncio.sleep(0.01)
        raise AssertionError("the HTTP server did not start")

    yield start
    for server, task, store in running:
        server.stop()
        await asyncio.wait_for(task, 10)
        store.close()


async def test_listing_data_sets_reads_no_content(serve: Serve) -> None:
    """Ten parallel list pages over eight 4 MB data sets: Python's peak allocation stays a small
    fraction of one data set (the content column is never read for a list)."""
    _, store, url = await serve()

    for i in range(8):
        add_dataset(store, csv_text(4 * MB, i), f"set-{i}")
    async with httpx.AsyncClient(base_url=url, headers=auth("viewer"), timeout=30) as client:
        r = await client.get("/api/datasets")  # warm: imports, pools
        assert r.status_code == 200 and len(r.json()) == 8
        tracemalloc.start()
        try:
            pages = await asyncio.gather(*(client.get("/api/datasets") for _ in range(10)))
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    print(f"list pages: peak {peak / MB:.2f} MB of Python allocations for 10 parallel pages")
    assert all(p.status_code == 200 and len(p.json()) == 8 for p in pages)
    assert "content" not in pages[0].json()[0]
    assert peak < 2 * MB, f"peak {peak / MB:.1f} MB of Python allocations for 10 list pages"


def _stalled_download(port: int, path: str) -> socket.socket:
    """A client that asks for ``path``, reads the status line's first bytes, and never reads again."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    token = TOKENS["viewer"]
    sock.sendall(
        f"GET {path} HTTP/1.1\r\nHost: cell\r\nAuthorization: Bearer {token}\r\n\r\n".encode("ascii")
    )
    sock.settimeout(5)
    assert sock.recv(12).startswith(b"HTTP/1.1 200")
    return sock


def _dropped(sock: socket.socket) -> bool:
    """Whether the server has closed (or reset) the connection, once the bytes in flight are read."""
    sock.settimeout(0.2)
    try:
        while True:
            chunk = sock.recv(1 << 20)
            if not chunk:
                return True
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


async def test_unread_downloads_hold_little_and_are_dropped(serve: Serve) -> None:
    """Ten clients that stop reading a 16 MB download: the server holds at most a chunk each, and
    drops them after ``http.write_timeout_s``; a client that reads gets every byte."""
    server, store, url = await serve(write_timeout_s=1.0)
    content = csv_text(16 * MB, 7)
    ident = add_dataset(store, content, "big")
    async with httpx.AsyncClient(base_url=url, headers=auth("viewer"), timeout=30) as client:
        r = await client.get(f"/api/datasets/{ident}/content")
    assert r.status_code == 200 and r.content == content.encode()
    assert r.headers["content-length"] == str(len(content))

    tracemalloc.start()
    try:
        base, _ = tracemalloc.get_traced_memory()
        socks = [await asyncio.to_thread(_stalled_download, server.port, f"/api/datasets/{ident}/content")]
        socks += [
            await asyncio.to_thread(_stalled_download, server.port, f"/api/datasets/{ident}/content")
            for _ in range(9)
        ]
        await asyncio.sleep(0.5)
        held, _ = tracemalloc.get_traced_memory()
        print(f"downloads: {(held - base) / MB:.1f} MB held by 10 unread downloads")
        assert (held - base) < 8 * MB, f"{(held - base) / MB:.1f} MB held by 10 unread downloads"
        deadline = time.monotonic() + 10.0
        while server.guard.write_timeouts < 10 and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        dropped = [await asyncio.to_thread(_dropped, s) for s in socks]
        await asyncio.sleep(0.2)
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        for s in socks:
            s.close()
    assert server.guard.write_timeouts == 10 and all(dropped), (server.guard, dropped)
    assert (after - base) < 2 * MB, f"{(after - base) / MB:.1f} MB still held after the drop"


def _late_total(text: str) -> float:
    for line in text.splitlines():
        if line.startswith("comp_daemon_rsi_late_replies_total "):
            return float(line.split()[1])
    raise AssertionError("comp_daemon_rsi_late_replies_total not in /metrics")


async def test_one_late_reply_count_and_one_ready_rule(tmp_path: Path, serve: Serve) -> None:
    """The late-reply count is the same in /metrics, /api/status and the loop event, across a restart
    of the real-time process; /ready, /api/status and the dashboard say not ready in FAULT."""
    daemon = Daemon(make_settings(tmp_path))
    runtime = LoopRuntime({}, calibration=None, safety=SafetySettings(), loop=JointLoopSettings())
    daemon.realtime.runtime = runtime  # type: ignore[assignment]  # the loop itself, in place of its view
    _, store, url = await serve(daemon.view)
    model = store.add_model(ModelDraft(kind="kinematic", order=None, artifact={}, stats={}, dataset_id=None))
    store.activate_model(model.id)
    stats = RsiServerStats(64)
    async with httpx.AsyncClient(base_url=url, headers=auth("viewer"), timeout=10) as client:
        before = _late_total((await client.get("/metrics")).text)
        seen = []
        for late, superseded in ((3, 5), (0, 2)):  # the second: a new real-time process, from zero
            stats.late, stats.superseded = late, superseded
            await daemon.telemetry.update(runtime, stats, {}, realtime="test", state="idle")
            await asyncio.sleep(0.4)  # a status snapshot is at most http.status_interval_s old
            status = (await client.get("/api/status")).json()
            metric = _late_total((await client.get("/metrics")).text) - before
            seen.append((status["daemon"]["loop"]["late_replies"], metric))
        assert seen == [(8, 8.0), (10, 10.0)], seen

        runtime.fault(FaultKind.NOT_SETTLED, "A2 not settled within 10 s")  # a freeze fault
        await asyncio.sleep(0.4)
        ready = await client.get("/ready")
        status = (await client.get("/api/status")).json()
    assert status["daemon"]["state"] == "fault"
    assert ready.status_code == 503 and status["ready"] is False
    assert ready.json()["reasons"] == status["reasons"]
    assert any(r.startswith("a fault is latched (not_settled") for r in status["reasons"]), status["reasons"]


async def test_status_under_50_clients_is_a_snapshot(serve: Serve) -> None:
    """50 clients polling /api/status for 3 s: the store is asked for the status at the snapshot's
    rate, not once per request, and the answers stay quick."""
    _, store, url = await serve(max_connections=256)
    calls = 0
    counts = store.target_counts

    def counted() -> dict[str, int]:
        nonlocal calls
        calls += 1
        return counts()

    store.target_counts = counted
    latencies: list[float] = []
    requests = 0

    async def poll(client: httpx.AsyncClient, until: float) -> None:
        nonlocal requests
        while time.monotonic() < until:
            t0 = time.perf_counter()
            r = await client.get("/api/status")
            latencies.append(time.perf_counter() - t0)
            assert r.status_code == 200 and r.json()["you"]["role"] == "viewer", r.text
            requests += 1

    limits = httpx.Limits(max_connections=60, max_keepalive_connections=60)
    async with httpx.AsyncClient(base_url=url, headers=auth("viewer"), timeout=30, limits=limits) as client:
        await client.get("/api/status")
        calls = 0
        t0 = time.monotonic()
        until = t0 + 3.0
        await asyncio.gather(*(poll(client, until) for _ in range(50)))
        elapsed = time.monotonic() - t0
    p50 = statistics.median(latencies)
    p99 = sorted(latencies)[int(0.99 * (len(latencies) - 1))]
    print(f"status: {requests} requests in {elapsed:.1f} s, p50 {p50 * 1e3:.0f} ms, p99 {p99 * 1e3:.0f} ms")
    print(f"status: {calls} snapshot builds")
    bound = elapsed / 0.25 + 4  # a build every 0.25 s, and a few on demand
    assert requests >= 2 * bound, f"only {requests} requests: too few to tell (a loaded machine?)"
    assert calls <= bound, f"{calls} store reads for {requests} requests"


async def test_thirty_small_uploads_at_once_all_fit(serve: Serve) -> None:
    """30 clients upload an 80 KB campaign at the same moment: the limit is on bytes in flight, not on
    the number of uploads, so none is refused."""
    from test_service_hostile import big_csv

    body = big_csv(80_000)
    _, store, url = await serve(max_connections=256)
    headers = {**auth("engineer"), "Content-Type": "text/csv"}
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=httpx.Limits(max_connections=40)) as client:
        answers = await asyncio.gather(
            *(client.post(f"/api/datasets?name=u{i}", content=body, headers=headers) for i in range(30))
        )
    codes = [r.status_code for r in answers]
    assert codes == [201] * 30, codes
    assert len(store.list_datasets()) == 30


def test_a_download_reads_the_content_as_it_was_when_it_started(tmp_path: Path) -> None:
    """The chunks come from a read transaction of their own: a data set deleted mid-download is
    still sent whole; one that is gone before is NotFoundError (404)."""
    from comp_daemon.service.store import NotFoundError

    store = Store(tmp_path / "store.sqlite3")
    try:
        content = csv_text(3 * MB, 1)
        ident = add_dataset(store, content, "one")
        reader = store.open_dataset_content(ident)
        first = reader.read(MB)
        store.delete_dataset(ident)
        rest = b"".join(iter(lambda: reader.read(MB), b""))
        reader.close()
        assert first + rest == content.encode() and reader.size == len(content)
        with pytest.raises(NotFoundError):
            store.open_dataset_content(ident)
    finally:
        store.close()
