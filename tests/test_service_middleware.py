"""The service's ASGI middleware on bare apps: an error answers the request only while no response has
started; once one has, the client gets what was sent and nothing after it."""

from __future__ import annotations

from typing import Any

import pytest
from starlette.types import Message, Receive, Scope, Send

from comp_daemon.service.api import BodyLimitMiddleware, InternalErrorMiddleware

HTTP: Scope = {"type": "http", "method": "POST", "path": "/x", "headers": []}


def chunks(*bodies: bytes) -> Receive:
    queue = [
        {"type": "http.request", "body": b, "more_body": i < len(bodies) - 1} for i, b in enumerate(bodies)
    ]

    async def receive() -> Message:
        return queue.pop(0)

    return receive


async def run(app: Any, receive: Receive) -> list[Message]:
    sent: list[Message] = []

    async def send(message: Message) -> None:
        sent.append(message)

    await app(HTTP, receive, send)
    return sent


def statuses(sent: list[Message]) -> list[int]:
    return [m["status"] for m in sent if m["type"] == "http.response.start"]


def failing_app(start_first: bool) -> Any:
    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        if start_first:
            await send({"type": "http.response.start", "status": 200, "headers": []})
        raise RuntimeError("boom")

    return app


def reading_app(start_first: bool) -> Any:
    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        if start_first:
            await send({"type": "http.response.start", "status": 200, "headers": []})
        while (await receive()).get("more_body"):
            pass
        await send({"type": "http.response.body", "body": b"read"})

    return app


@pytest.mark.parametrize(("start_first", "expected"), [(False, [500]), (True, [200])])
async def test_internal_error_is_answered_only_before_the_response_starts(
    start_first: bool, expected: list[int]
) -> None:
    sent = await run(InternalErrorMiddleware(failing_app(start_first)), chunks(b""))
    assert statuses(sent) == expected


@pytest.mark.parametrize(("start_first", "expected"), [(False, [413]), (True, [200])])
async def test_streamed_body_over_the_limit_is_answered_only_before_the_response_starts(
    start_first: bool, expected: list[int]
) -> None:
    sent = await run(BodyLimitMiddleware(reading_app(start_first), limit_bytes=8), chunks(b"12345", b"67890"))
    assert statuses(sent) == expected
    if not start_first:
        assert b"over the limit of 8 bytes" in sent[-1]["body"]


async def test_body_under_the_limit_passes() -> None:
    sent = await run(BodyLimitMiddleware(reading_app(False), limit_bytes=10), chunks(b"12345", b"67890"))
    assert sent == [{"type": "http.response.body", "body": b"read"}]
