"""HTTP fit jobs on a campaign without dir columns: directions inferred by default, ``infer_dir`` off."""

from __future__ import annotations

import dataclasses
from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import pytest
from service_client import in_process_service, job_done
from test_service_api import auth, make_settings

from comp_daemon.cli import main
from comp_daemon.data.dataset import read_dataset, write_dataset

SCENARIOS = Path(__file__).resolve().parents[1] / "comp_daemon" / "sim" / "scenarios"


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[httpx.AsyncClient]:
    settings = make_settings(tmp_path, jobs={"workers": 1})
    async with in_process_service(settings) as (c, _):
        yield c


async def test_fit_job_infers_directions_and_can_be_told_not_to(
    client: httpx.AsyncClient, tmp_path: Path
) -> None:
    full = tmp_path / "full.csv"
    scenario = str(SCENARIOS / "kr210-backlash.toml")
    assert main(["sim", "sample", "--scenario", scenario, "--n", "120", "--out", str(full)]) == 0
    nodir = tmp_path / "nodir.csv"
    write_dataset(dataclasses.replace(read_dataset(full), dir=None), nodir)
    up = await client.post(
        "/api/datasets?name=nodir",
        content=nodir.read_text(),
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert up.status_code == 201, up.text
    dataset_id = up.json()["id"]
    kinds = {k["name"]: k for k in (await client.get("/api/fits/kinds", headers=auth("viewer"))).json()}
    assert kinds["kriging"]["options"] and kinds["kriging-backlash"]["effects"]
    assert not kinds["chebyshev"]["options"]
    bad = await client.post(
        "/api/fits",
        json={"dataset_id": dataset_id, "model": "kinematic", "infer_dir": "maybe"},
        headers=auth("engineer"),
    )
    assert bad.status_code == 422
    jobs = {}
    for infer in (True, False):
        r = await client.post(
            "/api/fits",
            json={"dataset_id": dataset_id, "model": "kinematic+ratio+backlash", "infer_dir": infer},
            headers=auth("engineer"),
        )
        assert r.status_code == 202, r.text
        jobs[infer] = r.json()["id"]
    inferred = await job_done(client, jobs[True])
    assert inferred["state"] == "done", inferred["error"]
    stats = inferred["result"]["stats"]
    assert "inferred from the sign of each axis' last motion" in stats["directions"]
    assert stats["table2"]["model"]["3d"]["rms"] < 0.1
    refused = await job_done(client, jobs[False])
    assert refused["state"] == "failed" and "dir1..dir6" in (refused["error"] or "")
