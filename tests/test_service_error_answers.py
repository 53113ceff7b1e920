"""The service's error answers: the store refusals' table and where a validation error points."""

from __future__ import annotations

import httpx
import pytest
from fastapi import FastAPI

from comp_daemon.service.api import _install_error_handlers, validation_place
from comp_daemon.service.store import ConflictError, IdempotencyConflict, NotFoundError


@pytest.mark.parametrize(
    ("loc", "place"),
    [
        (["body", "targets", "2", "tx"], (3, "tx", "target")),
        (["body", "targets", "0"], (1, None, "target")),
        (["body", "poses", "4", "1"], (5, "a2", "pose")),
        (["body", "targets", "first", "tx"], (None, None, None)),
        (["body", "name"], (None, "name", None)),
        (["body", "probe_sigma_deg"], (None, "probe_sigma_deg", None)),
        (["query", "limit"], (None, "limit", None)),
        (["header", "idempotency-key"], (None, "idempotency-key", None)),
        (["path", "target_id"], (None, "target_id", None)),
        (["query"], (None, None, None)),
        ([], (None, None, None)),
    ],
)
def test_validation_place_names_the_row_and_column(loc: list[str], place: tuple[object, ...]) -> None:
    assert validation_place(loc) == place


@pytest.mark.parametrize(
    ("error", "status", "code"),
    [
        (NotFoundError("target", 7), 404, "not_found"),
        (IdempotencyConflict("key used with another request"), 409, "idempotency_conflict"),
        (ConflictError("target 7 is done"), 409, "conflict"),
    ],
)
async def test_store_refusals_answer_their_status_and_code(error: Exception, status: int, code: str) -> None:
    app = FastAPI()
    _install_error_handlers(app)

    @app.get("/refuse")
    async def refuse() -> None:
        raise error

    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as client:
        answer = await client.get("/refuse")
    assert answer.status_code == status
    body = answer.json()
    assert (body["error"], body["message"]) == (code, str(error))
