"""The HTTP service in-process for tests: its app with the lifespan run, an httpx client over ASGI,
and a wait for a job to end."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from typing import Any

import httpx
from test_service_api import auth

from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import Settings
from comp_daemon.service.store import Store


@contextlib.asynccontextmanager
async def in_process_service(
    settings: Settings, headers: dict[str, str] | None = None
) -> AsyncIterator[tuple[httpx.AsyncClient, Store]]:
    """The service of ``settings`` (its store opened, its lifespan started) and a client of it."""
    store = open_store(settings)
    try:
        app = create_app(settings, store)
        async with app.router.lifespan_context(app):
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(
                transport=transport, base_url="http://cell", headers=headers
            ) as client:
                yield client, store
    finally:
        store.close()


async def job_done(client: httpx.AsyncClient, job_id: int, limit_s: float = 90.0) -> dict[str, Any]:
    """The job once it has ended (done, failed or cancelled), read as a viewer."""
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        job = (await client.get(f"/api/jobs/{job_id}", headers=auth("viewer"))).json()
        if job["state"] in ("done", "failed", "cancelled"):
            return dict(job)
        await asyncio.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish")


async def upload_dataset(client: httpx.AsyncClient, csv_text: str, name: str) -> int:
    """Store a data set as an engineer; its id."""
    up = await client.post(
        f"/api/datasets?name={name}",
        content=csv_text,
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert up.status_code == 201, up.text
    return int(up.json()["id"])
