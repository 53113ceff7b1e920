"""``POST /api/batches/file``: a target file queued as a batch (the dashboard's drop zone), read by
the project's reader, refused with the file's row and column, nothing queued of a refused file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from service_client import in_process_service
from test_service_api import AXES, auth, make_settings

HEADER = "pose_id,a1,a2,a3,a4,a5,a6\n"


def axes_row(pose_id: str, **change: float) -> str:
    values = {**AXES, **change}
    return ",".join([pose_id, *(repr(values[f"a{k}"]) for k in range(1, 7))]) + "\n"


def post(client: Any, text: str, key: str, role: str = "operator", ctype: str = "text/csv") -> Any:
    return client.post(
        "/api/batches/file",
        params={"name": "rib-7.csv"},
        content=text.encode(),
        headers={**auth(role), "Idempotency-Key": key, "Content-Type": ctype},
    )


async def test_a_target_file_is_queued_once_per_key(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path)) as (client, _):
        text = HEADER + axes_row("rib-7-01") + axes_row("rib-7-02", a1=5.0) + axes_row("rib-7-03", a2=-80.0)
        r = await post(client, text, "file-1")
        assert r.status_code == 201, r.text
        batch = r.json()
        assert [t["request"]["pose_id"] for t in batch["targets"]] == ["rib-7-01", "rib-7-02", "rib-7-03"]
        assert batch["targets"][1]["request"]["a1"] == 5.0 and batch["source"] == "operator-1"
        again = await post(client, text, "file-1")
        assert again.status_code == 200 and again.json()["id"] == batch["id"]
        other = await post(client, HEADER + axes_row("rib-7-01"), "file-1")
        assert other.status_code == 409, other.text


async def test_tcp_targets_keep_their_orientation(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path)) as (client, _):
        text = "pose_id,tx,ty,tz,ta,tb,tc\np1,1800,200,1400,0,90,0\n"
        r = await post(client, text, "tcp-1")
        assert r.status_code == 201, r.text
        request = r.json()["targets"][0]["request"]
        assert (request["tx"], request["ty"], request["tz"], request["tb"]) == (1800.0, 200.0, 1400.0, 90.0)


async def test_refusals_name_the_files_row_and_column_and_queue_nothing(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path)) as (client, _):
        # the reader's refusal: row 3 of the file (header = row 1), column a3
        r = await post(client, HEADER + axes_row("p1") + axes_row("p2", a3=500.0), "bad-1")
        assert r.status_code == 422, r.text
        body = r.json()
        assert (body["row"], body["column"], body["row_label"]) == (3, "a3", "row"), body
        assert "outside the axis limits" in body["message"] and "rib-7.csv" in body["message"]
        # a reach refusal after reading: the target's file row, not its place in the batch
        r = await post(client, "pose_id,tx,ty,tz\np1,1800,200,1400\np2,90000,0,1400\n", "bad-2")
        assert r.status_code == 422, r.text
        assert (r.json()["row"], r.json()["column"]) == (3, "tx"), r.json()
        assert "cannot reach" in r.json()["message"]
        # both forms in one file: refused, not guessed
        both = "a1,a2,a3,a4,a5,a6,tx,ty,tz\n0,-90,90,0,45,0,1800,0,1400\n"
        r = await post(client, both, "bad-3")
        assert r.status_code == 422 and r.json()["column"] == "tx", r.text
        listed = await client.get("/api/targets", headers=auth("viewer"))
        assert listed.json() == []


async def test_roles_and_media_type(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path)) as (client, _):
        text = HEADER + axes_row("p1")
        assert (await post(client, text, "k", role="viewer")).status_code == 403
        r = await post(client, text, "k", ctype="application/json")
        assert r.status_code == 415 and "text/csv" in r.json()["message"]
        r = await client.post("/api/batches/file", content=text.encode(), headers={**auth("operator")})
        assert r.status_code == 422  # no Idempotency-Key


async def test_a_file_and_a_json_batch_over_max_batch_targets_are_refused_alike(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path, http={"max_batch_targets": 2})) as (client, store):
        text = HEADER + "".join(axes_row(f"p{i}", a1=float(i)) for i in range(3))
        by_file = await post(client, text, "big-file")
        by_json = await client.post(
            "/api/batches",
            json={"targets": [{**AXES, "a1": float(i), "pose_id": f"p{i}"} for i in range(3)]},
            headers={**auth("operator"), "Idempotency-Key": "big-json"},
        )
        for r in (by_file, by_json):
            assert r.status_code == 422, r.text
            assert r.json()["message"] == "batch of 3 targets is over the limit of 2 (http.max_batch_targets)"
        assert by_json.json()["column"] == "targets"
        assert store.list_targets() == []
        assert (
            await post(client, HEADER + axes_row("p0") + axes_row("p1", a1=1.0), "fits")
        ).status_code == 201
