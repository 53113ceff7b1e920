"""Queue a target file as a batch: ``POST /api/batches/file`` (operator), the dashboard's drop zone.

The body is a target file as ``compensate`` reads it (CSV, ``text/csv``; the data set format with
``kind="targets"``: ``pose_id`` and axis values ``a1..a6``, or a wanted TCP ``tx, ty, tz`` with an
optional ``ta, tb, tc``; ``payload_kg`` when given). It is read by the project's reader, so a refused
file is answered 422 with the reader's message and the file's row (header = row 1) and column; then
every target is checked as ``POST /api/batches`` checks it (reach, wrist singularity), and a refusal
there names the file's row too. Nothing of a refused file is queued. The ``Idempotency-Key`` rule is
that of ``POST /api/batches`` (the same key and file: the same batch, 200). A file from another
tool is read with the query parameters ``delimiter``, ``decimal_comma``, ``units`` (:mod:`.read_options`;
``euler`` too, though a target file has no probe).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response

from comp_daemon.data.columns import DatasetError
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.readers import parse_dataset
from comp_daemon.data.target import targets_of_dataset
from comp_daemon.service.routes.params import Operator, State
from comp_daemon.service.routes.read_options import ReadingQuery, options_of
from comp_daemon.service.routes.targets import (
    IdempotencyKey,
    check_batch_size,
    queue_batch,
    validate_targets,
)
from comp_daemon.service.schemas import BatchOut, ErrorOut
from comp_daemon.service.state import ApiError, ServiceState

router = APIRouter(tags=["targets"])

_CSV_TYPES = ("text/csv", "application/csv", "text/plain")
_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "A target file (CSV): pose_id and a1..a6, or tx, ty, tz with optional ta, tb, tc.",
        "content": {"text/csv": {"schema": {"type": "string"}}},
    }
}


def _read(text: bytes, name: str, svc: ServiceState, options: ReadOptions) -> list[dict[str, Any]]:
    """Read (as ``options`` say the file is written) and check the file; a refusal names the file's
    row (header = row 1) and column. Returns the targets' records (those ``POST /api/batches``
    queues)."""
    dataset = parse_dataset(
        text, source=name, limits_deg=svc.robot.axis_limits_deg, kind="targets", options=options
    )
    targets = targets_of_dataset(dataset)
    check_batch_size(svc, len(targets))
    try:
        validate_targets(targets, svc.robot, svc.settings.compensation.limits())
    except DatasetError as exc:
        index = (exc.row or 1) - 1
        raise DatasetError(
            exc.problem, source=name, row=int(dataset.row_numbers[index]), column=exc.column
        ) from None
    return [t.to_record() for t in targets]


@router.post(
    "/batches/file",
    status_code=201,
    response_model=BatchOut,
    summary="Queue a target file (CSV) as a batch, once per Idempotency-Key (operator)",
    openapi_extra=_BODY,
    responses={
        200: {"model": BatchOut, "description": "the batch queued earlier under this key"},
        409: {"model": ErrorOut, "description": "the key was used with another file"},
        413: {"model": ErrorOut, "description": "body over http.max_upload_bytes"},
        415: {"model": ErrorOut, "description": "not text/csv"},
        422: {
            "model": ErrorOut,
            "description": "a refused file; row (header = row 1) and column name the fault",
        },
    },
)
async def post_target_file(
    request: Request,
    response: Response,
    svc: State,
    who: Operator,
    idempotency_key: IdempotencyKey,
    reading: ReadingQuery,
    name: Annotated[str, Query(min_length=1, max_length=200, description="the file's name")] = "targets.csv",
) -> BatchOut:
    options = options_of(reading)  # refused before the body is read
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in _CSV_TYPES:
        raise ApiError(415, "unsupported_media_type", "send the target file as text/csv")
    limit = svc.settings.http.max_upload_bytes
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise ApiError(
                413, "too_large", f"upload over the limit of {limit} bytes (http.max_upload_bytes)"
            )
    records = await svc.run(_read, bytes(body), name, svc, options)
    return await queue_batch(svc, response, who, idempotency_key, records, "target file queued", file=name)
