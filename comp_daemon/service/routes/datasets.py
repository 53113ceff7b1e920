"""Data sets: upload (CSV or JSON records), list, fetch, delete.

An upload is validated whole by :mod:`comp_daemon.data.dataset` against the configured robot's
axis limits; a refused upload is answered 422 with the row (or record) and column at fault and
nothing is stored. What is stored is the canonical CSV of the data set (exact floats, unknown
columns kept), whatever the upload format; ``sha256`` is the hash of that text.

An upload never runs on the event loop: its body is streamed to a temporary file (in memory up to
1 MiB), then parsed, validated, rendered and summarised in a worker thread (over 1 MiB: in a
process of its own, at most ``http.max_concurrent_uploads`` such processes at once). The bytes of
uploads in flight are bounded by ``http.max_upload_bytes_in_flight`` (40 MB: two at the 20 MB limit,
or hundreds of small ones; a check takes memory and CPU in proportion to the size); an upload whose
declared length does not fit beside those in flight is answered 503 with ``Retry-After``.
JSON follows the file reader's rules (a key given twice is refused) and more: a lone surrogate or a
NUL in a string and an integer beyond any double are refused 422 with the value's path
(``$[3].a1``); a NUL in a CSV field is refused with its row and column.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Query, Request, Response
from starlette.datastructures import UploadFile
from starlette.requests import ClientDisconnect
from starlette.types import Receive, Scope, Send

from comp_daemon.common.logs import get_logger
from comp_daemon.service.routes.params import Engineer, Paging, State, Viewer
from comp_daemon.service.routes.read_options import OPTION_FIELDS, ReadingQuery, merged, options_of
from comp_daemon.service.schemas import MAX_ID, DatasetOut, ErrorOut, json_array
from comp_daemon.service.state import ApiError
from comp_daemon.service.store.artifacts import DatasetContent
from comp_daemon.service.uploads import Spool, UploadChecker, UploadRefused

router = APIRouter(tags=["datasets"])
_log = get_logger("comp_daemon.api.datasets")

DatasetId = Annotated[int, Path(ge=1, le=MAX_ID, description="data set id")]

#: a download's chunk: what one connection holds at most, beside the socket's buffer
CONTENT_CHUNK_BYTES = 256 * 1024
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
                        # how the file is written, as the query parameters of the same names
                        "delimiter": {"type": "string", "enum": [",", ";", "tab"]},
                        "decimal_comma": {"type": "boolean"},
                        "units": {"type": "string", "maxLength": 20},
                        "euler": {"type": "string", "maxLength": 40},
                    },
                    "additionalProperties": False,  # the form takes these parts only
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
    400: {"model": ErrorOut, "description": "the client went away before the upload ended"},
    413: {"model": ErrorOut, "description": "body over http.max_upload_bytes"},
    415: {"model": ErrorOut, "description": "not CSV, JSON or multipart"},
    422: {"model": ErrorOut, "description": "refused data set; row/column (JSON: path) name the fault"},
    503: {"model": ErrorOut, "description": "http.max_upload_bytes_in_flight bytes of uploads are in flight"},
}


async def _spool(request: Request, limit: int) -> Spool:
    """The request body, refused with 413 over ``limit`` bytes."""
    spool = Spool()
    try:
        async for chunk in request.stream():
            if spool.size + len(chunk) > limit:
                raise ApiError(
                    413, "too_large", f"upload over the limit of {limit} bytes (http.max_upload_bytes)"
                )
            await spool.write(chunk)
    except ClientDisconnect:
        spool.close()
        raise ApiError(400, "bad_request", "the client went away before the upload ended") from None
    except BaseException:
        spool.close()
        raise
    return spool


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
    reading: ReadingQuery,
    name: Annotated[str | None, Query(min_length=1, max_length=200)] = None,
    kind: Annotated[
        Literal["measurement", "any"],
        Query(description="measurement: needs a1..a6 and x, y, z; any: target files too"),
    ] = "measurement",
) -> DatasetOut:
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype != "multipart/form-data" and ctype not in _CSV_TYPES and ctype != "application/json":
        raise ApiError(
            415, "unsupported_media_type", "send text/csv, application/json or multipart/form-data"
        )
    options_of(reading)  # a wrong option is refused before the body is read
    checker: UploadChecker = request.app.state.uploads
    limit = svc.settings.http.max_upload_bytes
    declared = request.headers.get("content-length", "")
    size = min(int(declared), limit) if declared.isdigit() else limit
    budget = checker.budget
    if not budget.take(size):
        raise ApiError(
            503,
            "busy",
            f"{budget.in_flight} bytes of {budget.uploads} uploads are in flight; {size} more do not fit "
            f"under http.max_upload_bytes_in_flight ({budget.limit_bytes}); try again",
            retry_after_s=2,
        )
    try:
        fmt, source, spool, fields = await _receive(request, limit, name, ctype)
        try:
            options = options_of(merged(reading, fields))
            checked = await checker.check(spool, fmt, source, svc.robot.axis_limits_deg, kind, options)
        except UploadRefused as exc:
            raise ApiError(422, "invalid_dataset", exc.message, **exc.where) from None
        finally:
            await asyncio.to_thread(spool.close)
    finally:
        budget.give(size)
    record = await svc.run(
        svc.store.add_dataset,
        name=checked.name,
        format=fmt,
        content=checked.content,
        sha256=checked.sha256,
        rows=checked.rows,
        summary=checked.summary,
    )
    if checked.dataset is not None:
        svc.parsed.put(record.id, checked.dataset)
    _log.info("dataset stored", dataset_id=record.id, rows=record.rows, by=who.name)
    return DatasetOut.of(record)


async def _receive(
    request: Request, limit: int, name: str | None, ctype: str
) -> tuple[Literal["csv", "json"], str, Spool, dict[str, str]]:
    """(format, data set name, body, the form's reader options) of an upload."""
    if ctype != "multipart/form-data":
        spool = await _spool(request, limit)
        fmt: Literal["csv", "json"] = "json" if ctype == "application/json" else "csv"
        return fmt, (name or "upload").strip()[:200] or "upload", spool, {}
    form = await request.form(max_files=1, max_fields=4 + len(OPTION_FIELDS), max_part_size=64 * 1024)
    try:
        part = form.get("file")
        if not isinstance(part, UploadFile):
            raise ApiError(
                422, "invalid_request", "multipart upload needs a file part named 'file'", column="file"
            )
        if part.size is not None and part.size > limit:
            raise ApiError(
                413, "too_large", f"upload over the limit of {limit} bytes (http.max_upload_bytes)"
            )
        spool = Spool()
        await asyncio.to_thread(spool.write_from, part.file)
        form_name = form.get("name")
        name = (
            name or (form_name if isinstance(form_name, str) and form_name.strip() else None) or part.filename
        )
        is_json = (part.filename or "").lower().endswith(".json") or (part.content_type or "").endswith(
            "json"
        )
        fields = {k: v for k in OPTION_FIELDS if isinstance(v := form.get(k), str)}
    finally:
        await form.close()
    return ("json" if is_json else "csv"), (name or "upload").strip()[:200] or "upload", spool, fields


@router.get("/datasets", response_model=list[DatasetOut], summary="List data sets (newest first)")
async def list_datasets(
    svc: State,
    who: Viewer,
    page: Paging,
) -> Response:
    rows = await svc.run(svc.store.list_datasets, limit=page.limit, offset=page.offset)
    return json_array(DatasetOut.of(r) for r in rows)


@router.get(
    "/datasets/{dataset_id}",
    response_model=DatasetOut,
    summary="One data set's description",
    responses={404: {"model": ErrorOut}},
)
async def get_dataset(dataset_id: DatasetId, svc: State, who: Viewer) -> DatasetOut:
    return DatasetOut.of(await svc.run(svc.store.get_dataset, dataset_id))


class _StoredContent(Response):
    """A stored data set's CSV sent :data:`CONTENT_CHUNK_BYTES` at a time, read from the store chunk
    by chunk (never whole in memory); ends early when the client goes away. A client that stops
    reading is dropped by the server's write time limit (``http.write_timeout_s``)."""

    def __init__(self, content: DatasetContent, filename: str) -> None:
        self.content = content
        self.status_code = 200
        self.background = None
        self.media_type = "text/csv; charset=utf-8"
        self.init_headers(
            {
                "content-length": str(content.size),
                "content-disposition": f'attachment; filename="{filename}"',
            }
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        gone = asyncio.Event()

        async def watch() -> None:
            while (await receive())["type"] != "http.disconnect":
                pass
            gone.set()

        watcher = asyncio.create_task(watch())
        try:
            await send({"type": "http.response.start", "status": 200, "headers": self.raw_headers})
            left = self.content.size
            while left > 0 and not gone.is_set():
                chunk = await asyncio.to_thread(self.content.read, min(CONTENT_CHUNK_BYTES, left))
                if not chunk:
                    break
                left -= len(chunk)
                await send({"type": "http.response.body", "body": chunk, "more_body": left > 0})
            if left > 0 and not gone.is_set():  # the row changed under us: end the body short
                _log.warning("dataset content ended early", missing_bytes=left)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
        finally:
            watcher.cancel()
            await asyncio.to_thread(self.content.close)


@router.get(
    "/datasets/{dataset_id}/content",
    response_class=Response,  # errors are JSON (ErrorOut), the data set text/csv
    summary="The stored data set as CSV (streamed)",
    responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}}}, 404: {"model": ErrorOut}},
)
async def get_dataset_content(dataset_id: DatasetId, svc: State, who: Viewer) -> Response:
    content = await svc.run(svc.store.open_dataset_content, dataset_id)
    return _StoredContent(content, f"dataset-{dataset_id}.csv")


@router.delete(
    "/datasets/{dataset_id}",
    status_code=204,
    summary="Delete a data set (engineer); refused while a job uses it",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
async def delete_dataset(dataset_id: DatasetId, svc: State, who: Engineer) -> Response:
    await svc.run(svc.store.delete_dataset, dataset_id)
    svc.parsed.forget(dataset_id)
    _log.info("dataset deleted", dataset_id=dataset_id, by=who.name)
    return Response(status_code=204)
