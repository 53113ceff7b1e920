"""The loop's operator actions over HTTP: grating calibration and fault acknowledgement.

The routes are checked against a recording ``DaemonControl`` (roles, validation naming the pose and
axis, conflicts, 409 without a daemon); the daemon's own methods against a loop runtime in a latched
fault. The calibration itself on the simulated cell runs in the trial test (tests/test_trial_quick.py).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

import httpx
import pytest

from comp_daemon.daemon.app import Daemon
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.loop import LoopRuntime
from comp_daemon.rt.safety import FaultKind, SafetySettings, SafetyState
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import Settings, load_settings
from comp_daemon.service.daemon_view import DaemonControl, DaemonSnapshot, DaemonView, LoopStats

TOKENS = {
    "viewer": "viewer-token-0123456789abcdef",
    "operator": "operator-token-0123456789abcdef",
    "engineer": "engineer-token-0123456789abcdef",
}
HOME = [0.0, -85.0, 125.0, 0.0, -40.0, 0.0]


def auth(role: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[role]}"}


def make_settings(tmp_path: Path) -> Settings:
    return load_settings(
        None,
        store={"data_dir": str(tmp_path / "data")},
        auth={"tokens": [{"name": f"{r}-1", "role": r, "token": t} for r, t in TOKENS.items()]},
    )


class RecordingDaemon:
    """A DaemonView + DaemonControl that records what the routes ask of it."""

    def __init__(self) -> None:
        self.started: list[tuple[list[list[float]] | None, str]] = []
        self.refuse: str | None = None
        self.fault: dict[str, Any] | None = {
            "kind": "diverging",
            "reaction": "stop",
            "detail": "A2 diverged",
            "target_id": "7",
        }

    def snapshot(self) -> DaemonSnapshot:
        return DaemonSnapshot(state="fault" if self.fault else "idle", time=0.0)

    def readiness_reasons(self) -> list[str]:
        return []

    def loop_stats(self) -> LoopStats:
        return LoopStats(running=True)

    def start_grating_calibration(self, poses_deg: Sequence[Sequence[float]] | None, by: str) -> None:
        if self.refuse:
            raise RuntimeError(self.refuse)
        self.started.append((None if poses_deg is None else [list(p) for p in poses_deg], by))

    def grating_status(self) -> dict[str, Any]:
        return {
            "calibrating": bool(self.started),
            "calibration": None,
            "last_error": None,
            "started_at": None,
            "finished_at": None,
        }

    def acknowledge_fault(self, by: str) -> dict[str, Any] | None:
        cleared, self.fault = self.fault, None
        return cleared


@pytest.fixture
async def app_env(tmp_path: Path) -> AsyncIterator[tuple[httpx.AsyncClient, RecordingDaemon, Any]]:
    settings = make_settings(tmp_path)
    store = open_store(settings)
    daemon = RecordingDaemon()
    assert isinstance(daemon, DaemonView) and isinstance(daemon, DaemonControl)
    app = create_app(settings, store, daemon)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cell") as client:
            yield client, daemon, store
    store.close()


async def test_calibration_route_roles_validation_and_conflict(app_env: Any) -> None:
    client, daemon, store = app_env
    for role in ("viewer", "operator"):
        r = await client.post("/api/gratings/calibrate", headers=auth(role))
        assert r.status_code == 403, r.text
    assert daemon.started == []

    r = await client.post("/api/gratings/calibrate", headers=auth("engineer"))
    assert r.status_code == 202, r.text
    assert r.json()["calibrating"] is True
    assert daemon.started == [(None, "engineer-1")]

    poses = [HOME, [10.0, *HOME[1:]], [-10.0, *HOME[1:]]]
    r = await client.post("/api/gratings/calibrate", json={"poses": poses}, headers=auth("engineer"))
    assert r.status_code == 202, r.text
    assert daemon.started[-1] == (poses, "engineer-1")

    bad = [HOME, [*HOME[:2], 170.0, *HOME[3:]], HOME]  # A3 beyond +155
    r = await client.post("/api/gratings/calibrate", json={"poses": bad}, headers=auth("engineer"))
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["row"] == 2 and body["column"] == "a3" and "outside the axis limits" in body["message"]
    r = await client.post(
        "/api/gratings/calibrate", json={"poses": [HOME, HOME[:5], HOME]}, headers=auth("engineer")
    )
    assert r.status_code == 422 and r.json()["row"] == 2, r.text
    r = await client.post("/api/gratings/calibrate", json={"poses": [HOME, HOME]}, headers=auth("engineer"))
    assert r.status_code == 422, r.text  # fewer than three poses
    assert len(daemon.started) == 2

    daemon.refuse = "a target is active; calibrate between targets"
    r = await client.post("/api/gratings/calibrate", headers=auth("engineer"))
    assert r.status_code == 409 and r.json()["message"] == daemon.refuse

    r = await client.get("/api/gratings", headers=auth("viewer"))
    assert r.status_code == 200 and r.json()["calibrating"] is True
    kinds = [e.kind for e in store.list_events(limit=100)]
    assert kinds.count("gratings.started") == 2


async def test_reset_fault_route(app_env: Any) -> None:
    client, _, store = app_env
    r = await client.post("/api/loop/reset-fault", headers=auth("viewer"))
    assert r.status_code == 403
    r = await client.post("/api/loop/reset-fault", headers=auth("operator"))
    assert r.status_code == 200, r.text
    assert r.json()["cleared"]["kind"] == "diverging" and r.json()["daemon"]["state"] == "idle"
    events = [e for e in store.list_events(limit=100) if e.kind == "loop.fault_reset"]
    assert len(events) == 1 and events[0].message["by"] == "operator-1"
    r = await client.post("/api/loop/reset-fault", headers=auth("operator"))
    assert r.status_code == 200 and r.json()["cleared"] is None
    assert len([e for e in store.list_events(limit=100) if e.kind == "loop.fault_reset"]) == 1


async def test_routes_without_a_daemon(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    store = open_store(settings)
    app = create_app(settings, store)
    try:
        async with app.router.lifespan_context(app):
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://cell") as client:
                for method, path, role in (
                    ("GET", "/api/gratings", "viewer"),
                    ("POST", "/api/gratings/calibrate", "engineer"),
                    ("POST", "/api/loop/reset-fault", "operator"),
                ):
                    r = await client.request(method, path, headers=auth(role))
                    assert r.status_code == 409 and r.json()["error"] == "not_ready", (path, r.text)
    finally:
        store.close()


async def test_daemon_acknowledges_a_latched_fault_and_refuses_calibration_without_a_loop(
    tmp_path: Path,
) -> None:
    daemon = Daemon(make_settings(tmp_path))
    view = daemon.view  # what the HTTP service is given
    assert isinstance(view, DaemonView) and isinstance(view, DaemonControl)
    with pytest.raises(RuntimeError, match="no loop"):
        view.start_grating_calibration(None, "test")
    assert view.grating_status()["calibrating"] is False
    assert view.acknowledge_fault("test") is None
    assert view.snapshot().state == "starting" and view.readiness_reasons() == ["the daemon is starting"]
    runtime = LoopRuntime({}, calibration=None, safety=SafetySettings(), loop=JointLoopSettings())
    daemon.realtime.runtime = runtime  # type: ignore[assignment]  # the loop itself, in place of its view
    runtime.fault(FaultKind.DIVERGING, "A2 diverged")
    assert runtime.core.state is SafetyState.FAULT
    assert view.snapshot().state == "fault" and "A2 diverged" in (view.snapshot().hold_reason or "")
    cleared = view.acknowledge_fault("operator-1")
    assert cleared is not None and cleared["kind"] == "diverging" and cleared["detail"] == "A2 diverged"
    assert runtime.core.state is SafetyState.IDLE
    assert view.acknowledge_fault("operator-1") is None
