"""Data sets: upload (CSV or JSON records), list, fetch, delete.

An upload is validated whole by :mod:`comp_daemon.data.dataset` against the configured robot's
axis limits; a refused upload is answered 422 with the row (or record) and column at fault and
nothing is stored. What is stored is the canonical CSV of the data set (exact floats, unknown
columns kept), whatever the upload format; ``sha256`` is the hash of that text.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Path, Query, Request, Response
from fastapi.responses import PlainTextResponse
from starlette.datastructures import UploadFile

from comp_daemon.common.logs import get_logger
from comp_daemon.data.dataset import (
    Dataset,
    DatasetError,
    dataset_from_records,
    dataset_to_csv,
    parse_dataset,
)
from comp_daemon.service.auth import Principal, require
from comp_daemon.service.config import Role
from comp_daemon.service.schemas import DatasetOut, ErrorOut, json_array
from comp_daemon.service.state import ApiError, ServiceState, get_state

router = APIRouter(tags=["datasets"])
_log = get_logger("comp_daemon.api.datasets")

State = Annotated[ServiceState, Depends(get_state)]
Viewer = Annotated[Principal, Depends(require(Role.viewer, read=True))]
Engineer = Annotated[Principal, Depends(require(Role.engineer))]
DatasetId = Annotated[int, Path(ge=1, le=2**62, description="data set id")]

_CSV_TYPES = ("text/csv", "application/csv", "text/plain")
_UPLOAD_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "The data set: a CSV file (multipart part 'file', or the raw body as text/csv), "
        "or JSON records (a list of objects, or {'name': ..., 'records': [...]}).",
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {"type": "string", "format": "binary"},
                        "name": {"type": "string", "maxLength": 200},
                    },
                }
            },
            "text/csv": {"schema": {"type": "string"}},
            "application/json": {
                "schema": {
                    "oneOf": [
                        {"type": "array", "items": {"type": "object"}},
                        {
                            "type": "object",
                            "required": ["records"],
                            "properties": {
                                "name": {"type": "string", "maxLength": 200},
                                "records": {"type": "array", "items": {"type": "object"}},
                            },
                        },
                    ]
                }
            },
        },
    }
}
_REFUSED: dict[int | str, dict[str, Any]] = {
    413: {"model": ErrorOut, "description": "body over http.max_upload_bytes"},
    415: {"model": ErrorOut, "description": "not CSV, JSON or multipart"},
    422: {"model": ErrorOut, "description": "refused data set; row/column name the fault"},
}


def _json_records(data: bytes, source: str) -> tuple[list[Any], str | None]:
    try:
        text = data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DatasetError("not UTF-8 text", source=source, row=line) from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DatasetError(
            f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}", source=source, row=exc.lineno
        ) from None
    except RecursionError:
        raise DatasetError("JSON nested too deeply", source=source) from None
    if isinstance(doc, list):
        return doc, None
    if isinstance(doc, dict) and isinstance(doc.get("records"), list):
        name = doc.get("name")
        return doc["records"], name if isinstance(name, str) and name.strip() else None
    raise DatasetError("expected a list of records or an object with 'records' (a list)", source=source)


def _validate(
    data: bytes, fmt: Literal["csv", "json"], name: str, limits: Any, kind: Literal["measurement", "any"]
) -> tuple[Dataset, str]:
    if fmt == "csv":
        ds = parse_dataset(data, source=name, limits_deg=limits, min_rows=1, kind=kind)
    else:
        records, inner = _json_records(data, name)
        name = (inner or name)[:200]
        ds = dataset_from_records(records, source=name, limits_deg=limits, min_rows=1, kind=kind)
    return ds, name


@router.post(
    "/datasets",
    status_code=201,
    response_model=DatasetOut,
    summary="Upload a data set (engineer)",
    openapi_extra=_UPLOAD_BODY,
    responses=_REFUSED,
)
async def upload_dataset(
    request: Request,
    svc: State,
    who: Engineer,
    name: Annotated[str | None, Query(min_length=1, max_length=200)] = None,
    kind: Annotated[
        Literal["measurement", "any"],
        Query(description="measurement: needs a1..a6 and x, y, z; any: target files too"),
    ] = "measurement",
) -> DatasetOut:
    limit = svc.settings.http.max_upload_bytes
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    fmt: Literal["csv", "json"]
    if ctype == "multipart/form-data":
        form = await request.form(max_files=1, max_fields=4, max_part_size=64 * 1024)
        part = form.get("file")
        if not isinstance(part, UploadFile):
            raise ApiError(
                422, "invalid_request", "multipart upload needs a file part named 'file'", column="file"
            )
        data = await part.read(limit + 1)
        form_name = form.get("name")
        name = (
            name or (form_name if isinstance(form_name, str) and form_name.strip() else None) or part.filename
        )
        is_json = (part.filename or "").lower().endswith(".json") or (part.content_type or "").endswith(
            "json"
        )
        fmt = "json" if is_json else "csv"
        await form.close()
    elif ctype in _CSV_TYPES:
        data, fmt = await request.body(), "csv"
    elif ctype == "application/json":
        data, fmt = await request.body(), "json"
    else:
        raise ApiError(
            415, "unsupported_media_type", "send text/csv, application/json or multipart/form-data"
        )
    if len(data) > limit:
        raise ApiError(413, "too_large", f"upload over the limit of {limit} bytes (http.max_upload_bytes)")
    source = (name or "upload").strip()[:200] or "upload"
    ds, source = await svc.run(_validate, data, fmt, source, svc.robot.axis_limits_deg, kind)
    content = await svc.run(dataset_to_csv, ds)
    record = await svc.run(
        svc.store.add_dataset,
        name=source,
        format=fmt,
        content=content,
        sha256=ds.content_sha256,
        rows=len(ds),
        summary=ds.summary(),
    )
    _log.info("dataset stored", dataset_id=record.id, rows=record.rows, by=who.name)
    return DatasetOut.of(record)


@router.get("/datasets", response_model=list[DatasetOut], summary="List data sets (newest first)")
async def list_datasets(
    svc: State,
    who: Viewer,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> Response:
    rows = await svc.run(
        svc.store.list_datasets, limit=min(limit, svc.settings.http.max_page_items), offset=offset
    )
    return json_array(DatasetOut.of(r) for r in rows)


@router.get(
    "/datasets/{dataset_id}",
    response_model=DatasetOut,
    summary="One data set's description",
    responses={404: {"model": ErrorOut}},
)
async def get_dataset(dataset_id: DatasetId, svc: State, who: Viewer) -> DatasetOut:
    return DatasetOut.of(await svc.run(svc.store.get_dataset, dataset_id))


@router.get(
    "/datasets/{dataset_id}/content",
    response_class=PlainTextResponse,
    summary="The stored data set as CSV",
    responses={200: {"content": {"text/csv": {}}}, 404: {"model": ErrorOut}},
)
async def get_dataset_content(dataset_id: DatasetId, svc: State, who: Viewer) -> Response:
    record = await svc.run(svc.store.get_dataset, dataset_id, with_content=True)
    filename = f"dataset-{record.id}.csv"
    return Response(
        record.content or "",
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


@router.delete(
    "/datasets/{dataset_id}",
    status_code=204,
    summary="Delete a data set (engineer); refused while a job uses it",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
async def delete_dataset(dataset_id: DatasetId, svc: State, who: Engineer) -> Response:
    await svc.run(svc.store.delete_dataset, dataset_id)
    _log.info("dataset deleted", dataset_id=dataset_id, by=who.name)
    return Response(status_code=204)
