"""A campaign with three reflectors per pose uploaded over HTTP and fitted as a job."""

from __future__ import annotations

from pathlib import Path

import httpx
from service_client import job_done
from test_models_fit_http import client  # noqa: F401  (client: a fixture, used by name)
from test_service_api import auth

from comp_daemon.cli import main


async def test_three_target_campaign_is_accepted_and_fitted(
    client: httpx.AsyncClient,  # noqa: F811  (the fixture of test_models_fit_http)
    tmp_path: Path,
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
    job = await job_done(client, r.json()["id"])
    assert job["state"] == "done", job["error"]
    assert job["result"]["stats"]["table2"]["model"]["3d"]["rms"] < 0.1
    fit = job["result"]["stats"]["fit"]
    assert fit["targets"] == 3 and fit["identification"].startswith("6-DOF")
    assert len(fit["more_targets_mm"]) == 2
    assert "target2_x" in fit["identified"]
