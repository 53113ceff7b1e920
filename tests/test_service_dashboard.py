"""The dashboard served by a real uvicorn server, live events over SSE, and the event bus itself."""

from __future__ import annotations

import asyncio
import json
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from test_service_api import AXES, auth, make_settings

from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.daemon_view import DaemonSnapshot, JointStatus, LoopStats
from comp_daemon.service.events import CLOSING, EventBus
from comp_daemon.service.state import ServiceState

# ----------------------------------------------------------------------------------- event bus


async def test_bus_fans_out_filters_and_drops_oldest_for_slow_readers() -> None:
    bus = EventBus(queue_events=8)
    every = bus.subscribe()
    targets_only = bus.subscribe(frozenset({"target"}))
    for i in range(12):
        bus.publish("loop", {"i": i})
    bus.publish("target.done", {"target_id": 5})
    got = [await every.get(timeout=1) for _ in range(8)]
    assert [e.kind for e in got if e] == ["loop"] * 7 + ["target.done"]  # 5 oldest dropped
    assert every.take_dropped() == 5 and every.take_dropped() == 0
    only = await targets_only.get(timeout=1)
    assert only is not None and only.kind == "target.done" and await targets_only.get(timeout=0.01) is None
    sse = only.sse(dropped=2)
    assert sse.startswith(f"id: {only.seq}\nevent: target.done\ndata: ") and sse.endswith("\n\n")
    assert json.loads(sse.split("data: ", 1)[1]) == {
        "seq": only.seq,
        "kind": "target.done",
        "time": only.time,
        "data": {"target_id": 5},
        "dropped": 2,
    }
    every.close()
    assert bus.subscriber_count == 1
    bus.close()
    last = await targets_only.get(timeout=1)
    assert last is not None and last.kind == CLOSING
    late = bus.subscribe()  # e.g. a dashboard reconnecting while the server stops
    first = await late.get(timeout=1)
    assert first is not None and first.kind == CLOSING


async def test_bus_accepts_publishers_on_other_threads() -> None:
    bus = EventBus()
    sub = bus.subscribe()
    threads = [
        threading.Thread(target=lambda k=k: bus.publish("daemon.snapshot", {"k": k})) for k in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    seen = sorted([(await sub.get(timeout=2)).data["k"] for _ in range(4)])  # type: ignore[union-attr]
    assert seen == [0, 1, 2, 3]


# -------------------------------------------------------------------------- a real HTTP server


class _Server:
    def __init__(self, app: Any) -> None:
        self.config = uvicorn.Config(app, host="127.0.0.1", port=0, log_config=None, lifespan="on")
        self.server = uvicorn.Server(self.config)
        self.loop: asyncio.AbstractEventLoop | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.loop.run_until_complete(self.server.serve())
        self.loop.close()

    def __enter__(self) -> str:
        self.thread.start()
        for _ in range(500):
            if self.server.started:
                break
            self.thread.join(0.02)
        assert self.server.started, "uvicorn did not start"
        port = self.server.servers[0].sockets[0].getsockname()[1]
        return f"http://127.0.0.1:{port}"

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(20)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[str, ServiceState]]:
    settings = make_settings(tmp_path, http={"sse_keepalive_s": 0.2})
    store = open_store(settings)
    app = create_app(settings, store)
    with _Server(app) as url:
        yield url, app.state.svc
    store.close()


def test_dashboard_page_and_its_assets_are_served_locally(served: Any) -> None:
    url, _ = served
    with httpx.Client(base_url=url, timeout=10) as client:
        root = client.get("/", follow_redirects=False)
        assert root.status_code in (302, 307) and root.headers["location"] == "/dashboard/"
        page = client.get("/dashboard/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        refs = [r for r in re.findall(r'(?:src|href)="([^"]+)"', page.text) if not r.startswith("data:")]
        assert sorted(refs) == ["app.js", "style.css"]
        assert not re.search(r'(?:src|href)="(?:https?:)?//', page.text)  # no CDN, nothing remote
        js = client.get("/dashboard/app.js")
        css = client.get("/dashboard/style.css")
        assert js.status_code == 200 and "javascript" in js.headers["content-type"]
        assert css.status_code == 200 and css.headers["content-type"].startswith("text/css")
        assert "url(" not in css.text and "@import" not in css.text
        assert not re.search(r"""fetch\(\s*["'`]https?:""", js.text)
        # every element the script looks up by id exists in the page
        ids = set(re.findall(r'\$\("([\w-]+)"\)', js.text))
        missing = sorted(i for i in ids if f'id="{i}"' not in page.text)
        assert missing == []
        # the endpoints the script calls exist in the API
        paths = client.get("/openapi.json").json()["paths"]
        for call in set(re.findall(r'"(/api/[a-z/-]+)', js.text)):
            assert any(p == call or p.startswith(call.rstrip("/") + "/") for p in paths), call


def test_live_events_reach_an_sse_client(served: Any) -> None:
    url, svc = served
    with httpx.Client(base_url=url, timeout=10) as client:
        assert client.get("/api/events").status_code == 401
        with client.stream("GET", "/api/events", headers=auth("viewer")) as stream:
            assert stream.headers["content-type"].startswith("text/event-stream")
            lines = stream.iter_lines()
            events = _events(lines)
            hello = next(events)
            assert hello[0] == "hello" and hello[1]["daemon"]["state"] == "not running"
            # a batch posted over HTTP is announced on the stream
            r = client.post(
                "/api/batches",
                json={"targets": [AXES]},
                headers={**auth("operator"), "Idempotency-Key": "sse"},
            )
            assert r.status_code == 201
            kind, payload = _next_not_keepalive(events)
            assert kind == "batch.accepted" and payload["data"]["batch_id"] == r.json()["id"]
            # the daemon publishes its snapshot from its own code (here: this thread)
            snap = DaemonSnapshot(
                state="settling",
                time=1.0,
                current_target_id=1,
                joints=(
                    JointStatus(
                        joint=2,
                        target_deg=-90.0,
                        grating_deg=-90.0004,
                        error_deg=-0.0004,
                        encoder="ok",
                        reading_age_ms=3.0,
                    ),
                ),
                loop=LoopStats(
                    running=True, cycle_ms=12, cycles=1000, latency_p50_ms=0.08, latency_p99_ms=0.2
                ),
            )
            svc.bus.publish("daemon.snapshot", snap.to_dict())
            kind, payload = _next_not_keepalive(events)
            assert kind == "daemon.snapshot" and payload["data"]["joints"][0]["error_deg"] == -0.0004
            # closing the bus ends the stream (the server can stop without waiting for clients)
            assert svc.bus._loop is not None
            svc.bus._loop.call_soon_threadsafe(svc.bus.close)
            kind, _ = _next_not_keepalive(events)
            assert kind == CLOSING
            assert next(events, None) is None


def _events(lines: Iterator[str]) -> Iterator[tuple[str, Any]]:
    kind, data = None, []
    for line in lines:
        if line == "":
            if kind is not None or data:
                yield (kind or "message", json.loads("\n".join(data)) if data else None)
            kind, data = None, []
        elif line.startswith(":"):
            yield ("keepalive", None)
        elif line.startswith("event:"):
            kind = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].strip())


def _next_not_keepalive(events: Iterator[tuple[str, Any]]) -> tuple[str, Any]:
    for kind, payload in events:
        if kind != "keepalive":
            return kind, payload
    raise AssertionError("stream ended")
