"""Jobs in the process pool (outcomes, cancel, time limit); fits and diagnoses over HTTP."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from service_client import in_process_service, job_done
from test_service_api import auth, campaign_csv, make_settings

from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.data.target import Target
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.artifact import parse_model
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.robot.description import load_robot
from comp_daemon.service.config import JobSettings
from comp_daemon.service.jobs import JobKind, JobRunner
from comp_daemon.service.store import EventRecord, JobRecord, ModelDraft, Store

# ---- job functions: module level, so that worker processes can import them


def count_primes(limit: int, *, progress: Callable[..., None]) -> dict[str, Any]:
    found = 0
    for n in range(2, limit):
        if n % 2000 == 0:
            progress(n / limit, f"at {n}")
        if all(n % d for d in range(2, int(n**0.5) + 1)):
            found += 1
    return {"primes": found, "pid": os.getpid(), "nan": float("nan")}


def refuse_input(*, progress: Callable[..., None]) -> dict[str, Any]:
    raise ValueError("dataset 3, row 7, column 'x': not a number")


def crash(*, progress: Callable[..., None]) -> dict[str, Any]:
    raise RuntimeError("secret internals /etc/shadow")


def spin(seconds: float, *, progress: Callable[..., None]) -> dict[str, Any]:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        progress(0.5, f"pid {os.getpid()}")
        time.sleep(0.01)
    return {"spun": seconds}


def _draft(job: JobRecord, result: Any) -> ModelDraft:
    return ModelDraft(kind="primes", order=None, artifact=dict(result), stats={}, dataset_id=None)


async def _until(store: Store, job_id: int, states: tuple[str, ...], limit_s: float = 60.0) -> JobRecord:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        job = store.get_job(job_id)
        if job.state in states:
            return job
        await asyncio.sleep(0.05)
    raise AssertionError(f"job {job_id} still {store.get_job(job_id).state}")


async def test_runner_outcomes(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.sqlite3")
    heard: list[EventRecord] = []
    store.add_listener(heard.append)
    runner = JobRunner(
        store, JobSettings(workers=2, max_runtime_s=6.0)
    )  # a worker start fits on a loaded machine
    for kind in (
        JobKind("primes", count_primes, on_done=_draft),
        JobKind("refuse", refuse_input),
        JobKind("crash", crash),
        JobKind("spin", spin),
    ):
        runner.register(kind)
    runner.start()
    try:
        ok = store.create_job("primes", {})
        runner.launch(ok, (30_000,))
        bad = store.create_job("refuse", {})
        runner.launch(bad, ())
        done = await _until(store, ok.id, ("done", "failed"))
        assert done.state == "done", done.error
        assert done.result is not None and done.result["primes"] == 3245 and done.result["nan"] is None
        assert done.result["pid"] != os.getpid()  # it ran in a worker process, not here
        model = store.list_models()[0]
        assert model.job_id == ok.id and model.kind == "primes"
        assert any(e.kind == "job.progress" and e.job_id == ok.id for e in heard)
        assert [e.kind for e in store.list_events(job_id=ok.id)] == [
            "job.queued",
            "job.running",
            "model.added",
            "job.done",
        ]
        refused = await _until(store, bad.id, ("done", "failed"))
        assert refused.state == "failed" and refused.error == "dataset 3, row 7, column 'x': not a number"

        boom = store.create_job("crash", {})
        runner.launch(boom, ())
        crashed = await _until(store, boom.id, ("done", "failed"))
        assert crashed.state == "failed" and crashed.error is not None
        assert crashed.error.startswith("internal error (id ") and "secret" not in crashed.error

        long = store.create_job("spin", {})
        runner.launch(long, (30.0,))
        await _until(store, long.id, ("running",))
        cancelled = runner.cancel(long.id, by="test")
        assert cancelled.state == "cancelled"
        await runner.drain()
        await asyncio.sleep(0.3)
        await runner.drain()
        assert store.get_job(long.id).state == "cancelled" and store.get_job(long.id).result is None

        slow = store.create_job("spin", {})
        runner.launch(slow, (30.0,))  # over max_runtime_s = 6
        timed_out = await _until(store, slow.id, ("failed", "done"))
        assert timed_out.state == "failed" and "max_runtime_s" in (timed_out.error or "")

        # a worker killed under a job (OOM killer, kill -9): the job fails, the pool is renewed
        victim = store.create_job("spin", {})
        runner.launch(victim, (30.0,))
        deadline = time.monotonic() + 30
        while not (store.get_job(victim.id).message or "").startswith("pid ") and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        os.kill(int((store.get_job(victim.id).message or "pid 0").split()[1]), signal.SIGKILL)
        died = await _until(store, victim.id, ("failed", "done"))
        assert (
            died.state == "failed"
            and died.error == "the worker process ended unexpectedly (killed or out of memory)"
        )
        after = store.create_job("primes", {})
        runner.launch(after, (1000,))
        assert (await _until(store, after.id, ("done", "failed"))).state == "done"
    finally:
        await runner.drain()
        runner.shutdown()
        store.close()


@pytest.fixture
async def service(tmp_path: Path) -> AsyncIterator[tuple[httpx.AsyncClient, Store]]:
    settings = make_settings(tmp_path, jobs={"workers": 1})
    async with in_process_service(settings) as service:
        yield service


async def test_fit_compare_activate_and_diagnose_over_http(service: Any) -> None:
    client, _ = service
    up = await client.post(
        "/api/datasets?name=campaign",
        content=campaign_csv(120),
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert up.status_code == 201, up.text
    dataset_id = up.json()["id"]
    bad = await client.post(
        "/api/fits", json={"dataset_id": dataset_id, "model": "spline"}, headers=auth("engineer")
    )
    assert bad.status_code == 422 and bad.json()["column"] == "model"
    missing = await client.post(
        "/api/fits", json={"dataset_id": 999, "model": "kinematic"}, headers=auth("engineer")
    )
    assert missing.status_code == 404

    started = []
    for body in ({"model": "kinematic"}, {"model": "chebyshev", "order": 1}):
        r = await client.post("/api/fits", json={"dataset_id": dataset_id, **body}, headers=auth("engineer"))
        assert r.status_code == 202 and r.json()["state"] in ("queued", "running")
        started.append(r.json()["id"])
    diag = await client.post("/api/diagnoses", json={"dataset_id": dataset_id}, headers=auth("engineer"))
    assert diag.status_code == 202
    early = await client.get(f"/api/diagnoses/{diag.json()['id']}", headers=auth("viewer"))
    assert early.status_code == 409 and early.json()["error"] == "not_ready"

    results = [await job_done(client, job_id) for job_id in started]
    for job in results:
        assert job["state"] == "done", job["error"]
        t2 = job["result"]["stats"]["table2"]
        # a model that learnt the geometric errors beats the nominal twin by far on the check rows
        assert t2["model"]["3d"]["max"] < 0.2 * t2["nominal"]["3d"]["max"]
        assert job["result"]["stats"]["rows"] == {"fit": 90, "check": 30}
    models = (await client.get("/api/models", headers=auth("viewer"))).json()
    assert sorted(m["kind"] for m in models) == ["chebyshev", "kinematic"] and not any(
        m["active"] for m in models
    )
    ids = [m["id"] for m in models]
    # lists carry summaries; the single views carry the per-row errors and the fit's tables
    assert all("errors_3d_mm" not in m["stats"] and "table2" in m["stats"] for m in models)
    assert all(not isinstance(v, dict | list) for m in models for v in m["stats"]["fit"].values())
    one = (await client.get(f"/api/models/{ids[0]}", headers=auth("viewer"))).json()
    assert len(one["stats"]["errors_3d_mm"]["model"]) == 30 and "identifiability" in one["stats"]["fit"]
    listed = (await client.get("/api/jobs", headers=auth("viewer"))).json()
    fits = [j for j in listed if j["kind"] == "fit" and j["result"] is not None]
    assert fits and all("errors_3d_mm" not in j["result"]["stats"] for j in fits)
    assert (
        "errors_3d_mm"
        in (await client.get(f"/api/jobs/{fits[0]['id']}", headers=auth("viewer"))).json()["result"]["stats"]
    )
    cmp = (await client.get(f"/api/models/compare?ids={ids[0]}&ids={ids[1]}", headers=auth("viewer"))).json()
    assert [row["model_id"] for row in cmp["models"]] == ids
    nominal = cmp["nominal_by_dataset"][str(dataset_id)]
    assert len(nominal["errors_3d_mm"]) == 30 and set(nominal["table2"]) == {"n", "x", "y", "z", "3d"}
    artifact = (await client.get(f"/api/models/{ids[0]}/artifact", headers=auth("viewer"))).json()
    assert artifact["format"] == "comp-daemon-model" and artifact["kind"] in ("kinematic", "chebyshev")
    loaded = parse_model(json.dumps(artifact), source="api", robot=load_robot("kr210"))  # checksum verified
    assert loaded.model.kind == artifact["kind"]
    r = await client.post(f"/api/models/{ids[1]}/activate", headers=auth("engineer"))
    assert r.status_code == 200 and r.json()["active"]
    assert "no model is active" not in (await client.get("/ready")).json()["reasons"]
    # a data set in use by a finished job may go; its models stay
    report_job = await job_done(client, diag.json()["id"])
    assert report_job["state"] == "done", report_job["error"]
    assert report_job["result"] is None  # the report is fetched on its own, not with the job
    report = (await client.get(f"/api/diagnoses/{report_job['id']}", headers=auth("viewer"))).json()
    assert report["rows"] == {"fit": 90, "check": 30} and report["baseline"]["effect"] == "nominal"
    assert report["steps"][0]["effect"] == "geometric" and report["unmodelled"] == []
    html = await client.get(f"/api/diagnoses/{report_job['id']}/report.html", headers=auth("viewer"))
    assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
    assert "default-src 'none'" in html.headers["content-security-policy"]
    assert "<html" in html.text.lower() and "geometric" in html.text
    assert (await client.delete(f"/api/datasets/{dataset_id}", headers=auth("engineer"))).status_code == 204
    assert len((await client.get("/api/models", headers=auth("viewer"))).json()) == 2


def affinity(*, progress: Callable[..., None]) -> dict[str, Any]:
    return {"cpus": sorted(os.sched_getaffinity(0))}


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
async def test_workers_keep_to_their_cpus(tmp_path: Path) -> None:
    """``jobs.cpus``: the daemon keeps the fit workers off the real-time thread's CPU."""
    cpu = sorted(os.sched_getaffinity(0))[0]
    store = Store(tmp_path / "s.sqlite3")
    runner = JobRunner(store, JobSettings(workers=1, cpus=[cpu]))
    runner.register(JobKind("affinity", affinity))
    runner.start()
    try:
        job = store.create_job("affinity", {})
        runner.launch(job, ())
        done = await _until(store, job.id, ("done", "failed"))
        assert done.state == "done" and done.result == {"cpus": [cpu]}, done.error
    finally:
        await runner.drain()
        runner.shutdown()


def _campaign_with_directions_and_payload(n: int, seed: int = 0) -> str:
    """A KR210 with geometric errors, backlash and gravity compliance; dir1..dir6 and payload_kg."""
    robot = load_robot("kr210")
    rng = np.random.default_rng(seed)
    a = rng.uniform([-60, -120, 40, -90, 20, -90.0], [60, -40, 130, 90, 100, 90.0], (n, 6))
    dirs = rng.choice([-1, 1], size=(n, 6))
    payload = np.where(np.arange(n) % 2 == 0, 0.0, 100.0)
    truth = KinematicParams.from_robot(robot).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(["h2", "h3", "C2", "C3"], [0.005, 0.004, 2e-8, 3e-8])
    p = twin_tcp_mm(robot, truth, eff, a, dirs.astype(float), payload) + rng.normal(0.0, 0.01, (n, 3))
    head = "a1,a2,a3,a4,a5,a6,x,y,z," + ",".join(f"dir{k}" for k in range(1, 7)) + ",payload_kg,split"
    lines = [head]
    for i in range(n):
        cells = [repr(float(v)) for v in (*a[i], *p[i])] + [str(int(d)) for d in dirs[i]]
        lines.append(",".join([*cells, repr(float(payload[i])), "check" if i % 4 == 0 else "fit"]))
    return "\n".join(lines) + "\n"


async def test_every_kind_fits_over_http_and_compensates_once_active(service: Any) -> None:
    client, store = service
    kinds = (await client.get("/api/fits/kinds", headers=auth("viewer"))).json()
    names = [k["name"] for k in kinds]
    assert names == ["nominal", "kinematic", "chebyshev", "kriging", "kriging-backlash", "compliance", "poe"]
    assert next(k for k in kinds if k["name"] == "kriging-backlash")["needs"] == ["dir"]
    up = await client.post(
        "/api/datasets?name=effects",
        content=_campaign_with_directions_and_payload(160),
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert up.status_code == 201, up.text
    dataset_id = up.json()["id"]
    bad = await client.post(
        "/api/fits",
        json={"dataset_id": dataset_id, "model": "chebyshev:2", "order": 3},
        headers=auth("engineer"),
    )
    assert bad.status_code == 422 and "contradicts" in bad.json()["message"]
    models = (
        "nominal",
        "kinematic+ratio+backlash",
        "chebyshev:1",
        "kriging",
        "kriging-backlash",
        "compliance",
    )
    started = {}
    for name in models:
        r = await client.post(
            "/api/fits", json={"dataset_id": dataset_id, "model": name}, headers=auth("engineer")
        )
        assert r.status_code == 202, r.text
        started[name] = r.json()["id"]
    robot = load_robot("kr210")
    home = (5.0, -85.0, 120.0, 3.0, -40.0, 10.0)
    for name, job_id in started.items():
        job = await job_done(client, job_id)
        assert job["state"] == "done", (name, job["error"])
        stats = job["result"]["stats"]
        assert stats["fit"]["model"] == name and stats["rows"] == {"fit": 120, "check": 40}
        t2 = stats["table2"]
        if name != "nominal":
            assert t2["model"]["3d"]["mean"] < 0.5 * t2["nominal"]["3d"]["mean"], name
        record = next(m for m in store.list_models(limit=50) if m.job_id == job_id)
        assert record.kind == name.split("+")[0].split(":")[0]
        artifact = (await client.get(f"/api/models/{record.id}/artifact", headers=auth("viewer"))).json()
        assert artifact["kind"] == stats["artifact_kind"]
        # activation: the daemon's compensator loads the stored artifact and compensates with it (a target
        # inside the sampled axis ranges: a model is not used outside its validity region)
        assert (
            await client.post(f"/api/models/{record.id}/activate", headers=auth("engineer"))
        ).status_code == 200
        comp = ActiveModelCompensator(store, robot, [0, 1, 2], current_axes=lambda: home)
        out = comp(Target(axes_deg=(10.0, -80.0, 110.0, 0.0, 50.0, 0.0), payload_kg=100.0))
        assert out.model_id == record.id and out.info["predicted_residual_mm"] < 1e-5, name
