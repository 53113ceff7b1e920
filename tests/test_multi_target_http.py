"""A campaign with three reflectors per pose uploaded over HTTP and fitted as a job."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from test_service_api import auth, make_settings

from comp_daemon.cli import main
from comp_daemon.service.api import create_app, open_store


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[httpx.AsyncClient]:
    settings = make_settings(tmp_path, jobs={"workers": 1})
    store = open_store(settings)
    app = create_app(settings, store)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cell") as c:
            yield c
    store.close()


async def _done(client: httpx.AsyncClient, job_id: int) -> dict[str, Any]:
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        job = (await client.get(f"/api/jobs/{job_id}", headers=auth("viewer"))).json()
        if job["state"] in ("done", "failed", "cancelled"):
            return dict(job)
        await asyncio.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish")


async def test_three_target_campaign_is_accepted_and_fitted(
    client: httpx.AsyncClient, tmp_path: Path
) -> None:
    data = tmp_path / "three.csv"
    args = ["sim", "sample", "--scenario", "kr210-geometric", "--n", "80", "--targets", "3"]
    assert main([*args, "--out", str(data)]) == 0
    assert "x3,y3,z3" in data.read_text().splitlines()[0]
    up = await client.post(
        "/api/datasets?name=three",
        content=data.read_text(),
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert up.status_code == 201, up.text
    r = await client.post(
        "/api/fits", json={"dataset_id": up.json()["id"], "model": "kinematic"}, headers=auth("engineer")
    )
    assert r.status_code == 202, r.text
    job = await _done(client, r.json()["id"])
    assert job["state"] == "done", job["error"]
    assert job["result"]["stats"]["table2"]["model"]["3d"]["rms"] < 0.1
    fit = job["result"]["stats"]["fit"]
    assert fit["targets"] == 3 and fit["identification"].startswith("6-DOF")
    assert len(fit["more_targets_mm"]) == 2
    assert "target2_x" in fit["identified"]
