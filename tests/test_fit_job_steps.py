"""A fit job's progress over HTTP: which model is being fitted, and how many of its steps (the
cross-validation fits of its selection) are done and remain, while it runs."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import httpx
from service_client import job_done, upload_dataset
from test_models_fit_http import client  # noqa: F401  (the fixture: the service with one job worker)
from test_service_api import auth

from comp_daemon.cli import main

STEP = re.compile(
    r"^fitting chebyshev:cv \(order by cross-validation\): cross-validation fits (\d+) of 50, (\d+) to go$"
)


async def test_a_running_fit_job_says_which_model_and_how_many_steps_remain(
    client: httpx.AsyncClient,  # noqa: F811
    tmp_path: Path,
) -> None:
    data = tmp_path / "campaign.csv"
    argv = ["sim", "sample", "--scenario", "kr210-cell", "--n", "600", "--seed", "3", "--out", str(data)]
    assert main(argv) == 0
    dataset_id = await upload_dataset(client, data.read_text(), "campaign")
    r = await client.post(
        "/api/fits", json={"dataset_id": dataset_id, "model": "chebyshev:cv"}, headers=auth("engineer")
    )
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    seen: list[tuple[int, int]] = []
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 120.0
    while loop.time() < deadline:
        job = (await client.get(f"/api/jobs/{job_id}", headers=auth("viewer"))).json()
        if job["state"] not in ("queued", "running"):
            break
        match = STEP.match(job["message"] or "")
        if match:
            seen.append((int(match[1]), int(match[2])))
        await asyncio.sleep(0.02)
    final = await job_done(client, job_id)
    assert final["state"] == "done", final["error"]
    assert seen, "no step of the fit was seen while it ran"
    assert all(done + left == 50 for done, left in seen)
    assert [done for done, _ in seen] == sorted(done for done, _ in seen)
