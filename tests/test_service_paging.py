"""The list endpoints' page: `limit` and `offset` checked alike, `limit` cut to `http.max_page_items`."""

from __future__ import annotations

from pathlib import Path

from service_client import in_process_service
from test_service_api import AXES, auth, make_settings

LISTS = ("/api/datasets", "/api/jobs", "/api/models", "/api/diagnoses", "/api/targets")


async def test_list_pages_are_cut_to_max_page_items(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path, http={"max_page_items": 2})) as (client, _):
        targets = [{**AXES, "a1": float(i), "pose_id": f"P{i}"} for i in range(5)]
        headers = {**auth("operator"), "Idempotency-Key": "pages"}
        r = await client.post("/api/batches", json={"targets": targets}, headers=headers)
        assert r.status_code == 201, r.text

        async def pose_ids(query: str) -> list[str]:
            page = await client.get(f"/api/targets{query}", headers=auth("viewer"))
            assert page.status_code == 200, page.text
            return [t["request"]["pose_id"] for t in page.json()]

        assert await pose_ids("") == ["P0", "P1"]
        assert await pose_ids("?limit=1000&offset=3") == ["P3", "P4"]
        assert await pose_ids("?limit=1&offset=2") == ["P2"]
        for path in LISTS:
            for bad in ("limit=0", "limit=1001", "offset=-1", "offset=2147483649"):
                r = await client.get(f"{path}?{bad}", headers=auth("viewer"))
                assert r.status_code == 422, (path, bad, r.text)
            r = await client.get(f"{path}?limit=1000&offset=0", headers=auth("viewer"))
            assert r.status_code == 200, (path, r.text)


async def test_list_endpoints_document_the_same_page_query(tmp_path: Path) -> None:
    async with in_process_service(make_settings(tmp_path)) as (client, _):
        spec = (await client.get("/openapi.json")).json()
    for path in LISTS:
        params = {p["name"]: p for p in spec["paths"][path]["get"]["parameters"]}
        limit, offset = params["limit"], params["offset"]
        assert limit["in"] == offset["in"] == "query", path
        assert (limit["schema"]["minimum"], limit["schema"]["maximum"], limit["schema"]["default"]) == (
            1,
            1000,
            100,
        )
        assert (offset["schema"]["minimum"], offset["schema"]["maximum"], offset["schema"]["default"]) == (
            0,
            2**31,
            0,
        )
        assert not {"page", "svc", "request"} & set(params), path
