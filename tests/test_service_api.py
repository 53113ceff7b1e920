"""The HTTP API end to end (httpx over ASGI, a temporary SQLite store): data sets, auth, targets, errors."""

from __future__ import annotations

import io
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from comp_daemon.common.logs import bound, configure_logging, get_logger
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import load_robot
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import Settings, load_settings
from comp_daemon.service.store import ModelDraft, Store

TOKENS = {
    "viewer": "viewer-token-0123456789abcdef",
    "operator": "operator-token-0123456789abcdef",
    "engineer": "engineer-token-0123456789abcdef",
}
AXES = {"a1": 0.0, "a2": -90.0, "a3": 90.0, "a4": 0.0, "a5": 45.0, "a6": 0.0}


def auth(role: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[role]}"}


def make_settings(tmp_path: Path, **overrides: Any) -> Settings:
    base: dict[str, Any] = {
        "store": {"data_dir": str(tmp_path / "data")},
        "auth": {"tokens": [{"name": f"{r}-1", "role": r, "token": t} for r, t in TOKENS.items()]},
    }
    base.update(overrides)
    return load_settings(None, **base)


def campaign_csv(n: int = 40, seed: int = 0, noise_mm: float = 0.01) -> str:
    """A measurement campaign of a KR210 with small geometric errors (every 4th row held out to check)."""
    robot = load_robot("kr210")
    nominal = KinematicParams.from_robot(robot)
    rng = np.random.default_rng(seed)
    lo = np.array([-60, -120, 40, -90, 20, -90.0])
    hi = np.array([60, -40, 130, 90, 100, 90.0])
    a = rng.uniform(lo, hi, (n, 6))
    rad = ("theta", "alpha", "beta", "base_r")
    scale = np.array([2e-4 if name.startswith(rad) else 0.3 for name in PARAM_NAMES])
    true = nominal.apply(rng.normal(0.0, 1.0, len(PARAM_NAMES)) * scale)
    p = tcp_position_mm(true, axes_deg_to_q_rad(a, true.sign)) + rng.normal(0.0, noise_mm, (n, 3))
    lines = ["a1,a2,a3,a4,a5,a6,x,y,z,split"]
    for i in range(n):
        cells = [repr(float(v)) for v in (*a[i], *p[i])]
        lines.append(",".join([*cells, "check" if i % 4 == 0 else "fit"]))
    return "\n".join(lines) + "\n"


@pytest.fixture
async def env(tmp_path: Path) -> AsyncIterator[tuple[httpx.AsyncClient, Store, Settings]]:
    settings = make_settings(tmp_path, http={"max_upload_bytes": 200_000, "max_batch_targets": 50})
    store = open_store(settings)
    app = create_app(settings, store)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cell") as client:
            yield client, store, settings
    store.close()


# --------------------------------------------------------------------------------------- data sets


async def test_upload_csv_three_ways_then_fetch_and_delete(env: Any) -> None:
    client, store, _ = env
    csv = campaign_csv()
    r1 = await client.post(
        "/api/datasets?name=raw", content=csv, headers={**auth("engineer"), "Content-Type": "text/csv"}
    )
    assert r1.status_code == 201, r1.text
    d1 = r1.json()
    assert (
        d1["rows"] == 40
        and d1["name"] == "raw"
        and d1["summary"]["split"] == {"column": True, "fit": 30, "check": 10}
    )
    files = {"file": ("campaign.csv", io.BytesIO(csv.encode()), "text/csv")}
    r2 = await client.post("/api/datasets", files=files, headers=auth("engineer"))
    assert r2.status_code == 201, r2.text
    assert r2.json()["name"] == "campaign.csv" and r2.json()["sha256"] == d1["sha256"]
    header, *rows = csv.splitlines()
    records = [dict(zip(header.split(","), row.split(","), strict=True)) for row in rows]
    records = [{k: (v if k == "split" else float(v)) for k, v in rec.items()} for rec in records]
    r3 = await client.post(
        "/api/datasets", json={"name": "as-json", "records": records}, headers=auth("engineer")
    )
    assert r3.status_code == 201, r3.text
    assert r3.json()["format"] == "json" and r3.json()["sha256"] == d1["sha256"]  # same content, same hash

    listed = (await client.get("/api/datasets", headers=auth("viewer"))).json()
    assert [d["id"] for d in listed] == [r3.json()["id"], r2.json()["id"], d1["id"]]
    content = await client.get(f"/api/datasets/{d1['id']}/content", headers=auth("viewer"))
    assert content.status_code == 200 and content.headers["content-type"].startswith("text/csv")
    assert content.text.splitlines()[0].split(",")[:9] == ["a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z"]
    assert len(content.text.splitlines()) == 41
    gone = await client.delete(f"/api/datasets/{d1['id']}", headers=auth("engineer"))
    assert gone.status_code == 204
    assert (await client.get(f"/api/datasets/{d1['id']}", headers=auth("viewer"))).status_code == 404
    assert len(store.list_datasets()) == 2


@pytest.mark.parametrize(
    ("mutate", "row", "column", "words"),
    [
        (
            lambda lines: lines.__setitem__(3, lines[3].replace(lines[3].split(",")[1], "abc", 1)),
            4,
            "a2",
            "number",
        ),
        (
            lambda lines: lines.__setitem__(5, lines[5].replace(lines[5].split(",")[0], "400", 1)),
            6,
            "a1",
            "limits",
        ),
        (lambda lines: lines.__setitem__(7, lines[7].rsplit(",", 1)[0] + ",train"), 8, "split", "fit"),
        (lambda lines: lines.__setitem__(0, lines[0].replace(",z,", ",q,")), 1, "z", "missing"),
    ],
)
async def test_bad_csv_is_refused_with_row_and_column_and_nothing_stored(
    env: Any, mutate: Any, row: int | None, column: str, words: str
) -> None:
    client, store, _ = env
    lines = campaign_csv().splitlines()
    mutate(lines)
    r = await client.post(
        "/api/datasets",
        content="\n".join(lines) + "\n",
        headers={**auth("engineer"), "Content-Type": "text/csv"},
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["error"] == "invalid_dataset"
    assert body.get("row") == row and body["column"] == column
    if row is not None:
        assert f"row {row}" in body["message"]
    assert column in body["message"] and words in body["message"]
    assert store.list_datasets() == [] and store.list_events(limit=1000)[-1].kind == "store.recovered"


async def test_bad_json_and_size_and_type_limits(env: Any) -> None:
    client, store, _ = env
    r = await client.post(
        "/api/datasets",
        content=b'[{"a1": 1,',
        headers={**auth("engineer"), "Content-Type": "application/json"},
    )
    assert r.status_code == 422 and "invalid JSON" in r.json()["message"]
    rec = {**AXES, "x": 1.0, "y": 2.0, "z": "3"}
    r = await client.post("/api/datasets", json=[rec], headers=auth("engineer"))
    assert r.status_code == 422 and r.json()["row"] == 1 and r.json()["column"] == "z"
    assert r.json()["row_label"] == "record"
    big = "a1,a2,a3,a4,a5,a6,x,y,z\n" + "0,-90,90,0,45,0,1,2,3\n" * 12_000  # > 200 kB + multipart slack
    r = await client.post(
        "/api/datasets", content=big, headers={**auth("engineer"), "Content-Type": "text/csv"}
    )
    assert r.status_code == 413 and "max_upload_bytes" in r.json()["message"]
    r = await client.post(
        "/api/datasets", content=b"x", headers={**auth("engineer"), "Content-Type": "image/png"}
    )
    assert r.status_code == 415
    assert store.list_datasets() == []


# ------------------------------------------------------------------------------------------- auth

WRITES: list[tuple[str, str, str, dict[str, Any] | None]] = [
    # (method, path, least role, json body)
    ("POST", "/api/datasets", "engineer", None),
    ("DELETE", "/api/datasets/1", "engineer", None),
    ("POST", "/api/fits", "engineer", {"dataset_id": 1, "model": "kinematic"}),
    ("POST", "/api/diagnoses", "engineer", {"dataset_id": 1}),
    ("POST", "/api/jobs/1/cancel", "engineer", None),
    ("POST", "/api/models/1/activate", "engineer", None),
    ("POST", "/api/batches", "operator", {"targets": [AXES]}),
    ("POST", "/api/batches/1/cancel", "operator", None),
    ("POST", "/api/targets/1/cancel", "operator", None),
    ("POST", "/api/targets/1/requeue", "operator", None),
]
READS = [
    "/api/status",
    "/api/datasets",
    "/api/jobs",
    "/api/models",
    "/api/targets",
    "/api/diagnoses",
    "/api/events/log",
]
ORDER = ["viewer", "operator", "engineer"]


async def test_auth_matrix(env: Any) -> None:
    client, _, _ = env
    for method, path, least, body in WRITES:
        headers = {"Idempotency-Key": "auth-matrix"}
        r = await client.request(method, path, json=body, headers=headers)
        assert r.status_code == 401, (method, path, r.status_code)
        assert r.headers["www-authenticate"] == "Bearer"
        r = await client.request(
            method, path, json=body, headers={**headers, "Authorization": "Bearer wrong-token-0123456789"}
        )
        assert r.status_code == 401, (method, path)
        for role in ORDER:
            r = await client.request(method, path, json=body, headers={**headers, **auth(role)})
            if ORDER.index(role) < ORDER.index(least):
                assert r.status_code == 403, (method, path, role, r.status_code)
                assert least in r.json()["message"]
            else:
                assert r.status_code not in (401, 403), (method, path, role, r.text)
    for path in READS:
        assert (await client.get(path)).status_code == 401, path
        assert (await client.get(path, headers={"Authorization": "Basic dXNlcjpwYXNz"})).status_code == 401
        for role in ORDER:
            assert (await client.get(path, headers=auth(role))).status_code == 200, (path, role)
    for path in ["/health", "/ready", "/metrics", "/dashboard/", "/openapi.json"]:
        assert (await client.get(path)).status_code in (200, 503), path


async def test_anonymous_read_setting(tmp_path: Path) -> None:
    settings = make_settings(
        tmp_path,
        auth={
            "anonymous_read": True,
            "anonymous_metrics": False,
            "tokens": [{"name": "op", "role": "operator", "token": TOKENS["operator"]}],
        },
    )
    store = open_store(settings)
    app = create_app(settings, store)
    async with app.router.lifespan_context(app):
        async with httpx.AsyncClient(
            transport=httpx.ASGITransport(app=app), base_url="http://cell"
        ) as client:
            assert (await client.get("/api/targets")).status_code == 200
            assert (await client.get("/metrics")).status_code == 401
            assert (
                await client.post("/api/batches", json={"targets": [AXES]}, headers={"Idempotency-Key": "k"})
            ).status_code == 401
            r = await client.get("/api/status")
            assert r.json()["you"] == {"name": "anonymous", "role": "viewer"}
    store.close()


# ---------------------------------------------------------------------------------------- targets


async def test_idempotent_batch_post(env: Any) -> None:
    client, store, _ = env
    targets = [{**AXES, "a1": float(i), "pose_id": f"H{i}"} for i in range(3)]
    headers = {**auth("operator"), "Idempotency-Key": "MES-2024-0001"}
    r1 = await client.post("/api/batches", json={"targets": targets}, headers=headers)
    assert r1.status_code == 201, r1.text
    first = r1.json()
    assert [t["seq"] for t in first["targets"]] == [1, 2, 3] and all(
        t["state"] == "queued" for t in first["targets"]
    )
    # same body, other spelling (key order, spacing, 1 vs 1.0): the same batch, nothing queued again
    reordered = [dict(reversed(list(t.items()))) for t in targets]
    reordered[0]["a2"] = -90
    r2 = await client.post(
        "/api/batches",
        content=json.dumps({"targets": reordered}, indent=2),
        headers={**headers, "Content-Type": "application/json"},
    )
    assert r2.status_code == 200 and r2.json() == first
    r3 = await client.post("/api/batches", json={"targets": targets[:2]}, headers=headers)
    assert r3.status_code == 409 and r3.json()["error"] == "idempotency_conflict"
    assert len(store.list_targets()) == 3
    # queries by batch and by id
    batch = (await client.get(f"/api/batches/{first['id']}", headers=auth("viewer"))).json()
    assert batch == first
    one = (await client.get(f"/api/targets/{first['targets'][1]['id']}", headers=auth("viewer"))).json()
    assert one["request"]["pose_id"] == "H1"
    by_batch = (
        await client.get(f"/api/targets?batch_id={first['id']}&state=queued", headers=auth("viewer"))
    ).json()
    assert [t["id"] for t in by_batch] == [t["id"] for t in first["targets"]]


async def test_batch_validation(env: Any) -> None:
    client, store, _ = env
    h = {**auth("operator"), "Idempotency-Key": "v1"}
    r = await client.post("/api/batches", json={"targets": [AXES]}, headers=auth("operator"))
    assert r.status_code == 422 and "idempotency-key" in r.json()["message"].lower()
    r = await client.post("/api/batches", json={"targets": [AXES, {**AXES, "a3": 500.0}]}, headers=h)
    assert r.status_code == 422 and (r.json()["row"], r.json()["column"]) == (2, "a3")
    assert "target 2" in r.json()["message"] and "limits" in r.json()["message"]
    r = await client.post("/api/batches", json={"targets": [AXES, {"a1": 1.0, "a2": 2.0}]}, headers=h)
    assert r.status_code == 422 and r.json()["row"] == 2
    r = await client.post("/api/batches", json={"targets": [AXES, {**AXES, "A1": 1.0}]}, headers=h)
    assert r.status_code == 422 and (r.json()["row"], r.json()["column"]) == (2, "A1")
    r = await client.post(
        "/api/batches",
        json={"targets": [{"tx": 1500.0, "ty": 0.0, "tz": 1200.0, "ta": 0.0, "tb": 90.0, "tc": 5.0}]},
        headers=h,
    )
    assert r.status_code == 201, r.text  # a wanted TCP pose instead of axis values
    r = await client.post(
        "/api/batches", json={"targets": [AXES] * 51}, headers={**h, "Idempotency-Key": "v2"}
    )
    assert r.status_code == 422 and "max_batch_targets" in r.json()["message"]
    r = await client.post("/api/batches", json={"targets": []}, headers={**h, "Idempotency-Key": "v3"})
    assert r.status_code == 422
    assert len(store.list_targets()) == 1


async def test_cancel_and_requeue(env: Any) -> None:
    client, store, _ = env
    r = await client.post(
        "/api/batches", json={"targets": [AXES] * 4}, headers={**auth("operator"), "Idempotency-Key": "c"}
    )
    ids = [t["id"] for t in r.json()["targets"]]
    started = store.claim_next_target()
    assert started is not None and started.id == ids[0]
    r = await client.post(f"/api/targets/{ids[0]}/cancel", headers=auth("operator"))
    assert r.status_code == 409 and "compensating" in r.json()["message"]
    r = await client.post(f"/api/targets/{ids[1]}/cancel", headers=auth("operator"))
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    r = await client.post(f"/api/batches/{r.json()['batch_id']}/cancel", headers=auth("operator"))
    assert [t["id"] for t in r.json()] == ids[2:]
    store.interrupt_active("stopped by SIGTERM")
    r = await client.post(f"/api/targets/{ids[0]}/requeue", headers=auth("operator"))
    assert r.status_code == 200 and r.json()["state"] == "queued"
    assert (await client.get("/api/targets/999999", headers=auth("viewer"))).status_code == 404
    assert (await client.get("/api/targets/0", headers=auth("viewer"))).status_code == 422
    assert (await client.get(f"/api/targets/{2**70}", headers=auth("viewer"))).status_code == 422


# ------------------------------------------------------------------------------ system endpoints


async def test_ready_metrics_status_and_events_log(env: Any) -> None:
    client, store, _ = env
    r = await client.get("/ready")
    assert r.status_code == 503
    assert r.json()["reasons"] == [
        "the real-time loop is not running (no daemon attached to this service)",
        "no model is active",
    ]
    model = store.add_model(ModelDraft(kind="kinematic", order=None, artifact={}, stats={}, dataset_id=None))
    await client.post(f"/api/models/{model.id}/activate", headers=auth("engineer"))
    r = await client.get("/ready")
    assert r.status_code == 503 and r.json()["reasons"] == [
        "the real-time loop is not running (no daemon attached to this service)"
    ]
    await client.post(
        "/api/batches", json={"targets": [AXES] * 3}, headers={**auth("operator"), "Idempotency-Key": "m"}
    )
    text = (await client.get("/metrics")).text
    assert "comp_daemon_target_queue_depth 3.0" in text
    for name in (
        "comp_daemon_loop_reply_latency_seconds_bucket",
        "comp_daemon_rsi_late_replies_total",
        "comp_daemon_encoder_faults_total",
        "comp_daemon_loop_running",
        'comp_daemon_rsi_stops_total{cause="late_replies"} ',  # every cause exposed from the start
        'comp_daemon_build_info{version="',
        "process_resident_memory_bytes",
    ):
        assert name in text
    status = (await client.get("/api/status", headers=auth("viewer"))).json()
    assert status["rsi"] is None  # no daemon attached: no RSI sessions to report
    assert status["targets"]["queued"] == 3 and status["active_model"]["id"] == model.id
    assert status["daemon"]["state"] == "not running" and status["ready"] is False
    log = (await client.get("/api/events/log?limit=10", headers=auth("viewer"))).json()
    assert [e["kind"] for e in log][-2:] == ["model.activated", "batch.accepted"]
    spec = (await client.get("/openapi.json")).json()
    assert {"/api/batches", "/api/datasets", "/api/fits", "/api/models/compare", "/ready"} <= set(
        spec["paths"]
    )


async def test_internal_errors_do_not_leak(env: Any) -> None:
    client, store, _ = env
    logs = io.StringIO()
    configure_logging("INFO", "json", stream=logs)
    store.close()  # the database goes away under the service: an internal error, not the user's
    try:
        r = await client.get("/api/targets", headers=auth("viewer"))
    finally:
        configure_logging("INFO", "console")
    assert r.status_code == 500
    body = r.json()
    assert body["error"] == "internal" and body["message"] == "internal error" and len(body["error_id"]) == 12
    assert "sqlite" not in r.text.lower() and "Traceback" not in r.text
    logged = [json.loads(line) for line in logs.getvalue().splitlines()]
    entry = next(e for e in logged if e.get("error_id") == body["error_id"])  # logged under that id
    assert entry["event"] == "internal error" and "ProgrammingError" in entry["exception"]


def test_logs_are_json_with_ids_bound(tmp_path: Path) -> None:
    buffer = io.StringIO()
    configure_logging("INFO", "json", stream=buffer)
    try:
        with bound(target_id=17, job_id=4):
            get_logger("comp_daemon.test").info("target settled", error_deg=0.0004)
        get_logger("comp_daemon.test").info("outside")
    finally:
        configure_logging("INFO", "console")
    first, second = (json.loads(line) for line in buffer.getvalue().splitlines())
    assert first["event"] == "target settled" and first["target_id"] == 17 and first["job_id"] == 4
    assert (
        first["level"] == "info"
        and first["logger"] == "comp_daemon.test"
        and first["timestamp"].endswith("Z")
    )
    assert "target_id" not in second


def test_json_array_is_the_page_pydantic_would_serialise() -> None:
    """Lists are serialised one item at a time (the real-time thread gets the GIL between items);
    the bytes are those of serialising the whole page at once."""
    import json

    from pydantic import TypeAdapter

    from comp_daemon.service.schemas import ErrorOut, json_array

    items = [ErrorOut(error="e", message=f"m{i} ü \u2028", row=i, column=None) for i in range(5)]
    body = json_array(items).body
    assert body == TypeAdapter(list[ErrorOut]).dump_json(items)
    third = json.loads(body)[3]
    assert third["message"] == "m3 ü \u2028" and third["row"] == 3 and third["column"] is None
    assert json_array([]).body == b"[]"
