"""The HTTP service: ``create_app(settings, store, daemon_view=None) -> FastAPI``.

The daemon opens the store with :func:`open_store` (which runs the recovery), builds the app and
serves it with :func:`comp_daemon.service.http_server.build_http_server` in its own event loop,
beside the RSI loop. Nothing here blocks that loop: store calls go through ``asyncio.to_thread``,
fits and diagnoses run in a process pool (:mod:`comp_daemon.service.jobs`), uploads are checked in
a thread or a process of their own (:mod:`comp_daemon.service.uploads`), metrics are rendered in a
thread.

Routes (details in the OpenAPI description at ``/openapi.json``):

- ``/health`` (liveness), ``/ready`` (200 or 503 with reasons), ``/metrics`` (Prometheus);
- ``/api/status``, ``/api/events`` (server-sent events), ``/api/events/log``;
- ``/api/datasets``, ``/api/fits``, ``/api/jobs``, ``/api/models``, ``/api/diagnoses``;
- ``/api/batches``, ``/api/targets``;
- ``/dashboard/`` (static files; ``/`` redirects there).

Errors: every error body is ``{"error": code, "message": text, ...}``; an unexpected exception is
logged with a fresh ``error_id`` and answered 500 with only that id (no internals).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from comp_daemon import __version__
from comp_daemon.common.logs import get_logger
from comp_daemon.data.columns import AXIS_COLUMNS, DatasetError
from comp_daemon.robot.description import load_robot
from comp_daemon.service import metrics
from comp_daemon.service.auth import AuthError, TokenTable
from comp_daemon.service.config import Settings
from comp_daemon.service.daemon_view import DaemonView, DetachedDaemonView
from comp_daemon.service.events import EventBus
from comp_daemon.service.jobs import JobKind, JobRunner
from comp_daemon.service.state import ApiError, ServiceState
from comp_daemon.service.status import StatusBoard
from comp_daemon.service.store import (
    TARGET_FINAL_STATES,
    ConflictError,
    EventRecord,
    IdempotencyConflict,
    NotFoundError,
    Store,
    StoreDamagedError,
    StoreFullError,
)
from comp_daemon.service.store import files as store_files
from comp_daemon.service.uploads import UploadChecker

__all__ = ["ApiError", "create_app", "open_store"]

_log = get_logger("comp_daemon.api")
STATIC_DIR = Path(__file__).resolve().parent / "static"
_MULTIPART_OVERHEAD_BYTES = 64 * 1024


def open_store(settings: Settings) -> Store:
    """Open the configured store, apply migrations, run the recovery and prune old events.

    Refused with :class:`~comp_daemon.service.store.StoreDamagedError` (one line: what, where, how
    to recover) when the database is damaged (``PRAGMA quick_check``), or missing or empty where a
    store existed (:mod:`comp_daemon.service.store.files`); a full disk is
    :class:`~comp_daemon.service.store.StoreFullError`."""
    db_path, backup_dir = settings.store.db_path, settings.store.backup_path
    store_files.refuse_if_lost(db_path, backup_dir)
    started = time.perf_counter()
    try:
        store = Store(
            db_path,
            synchronous=settings.store.synchronous,
            busy_timeout_ms=settings.store.busy_timeout_ms,
            check=True,
        )
    except StoreDamagedError as exc:
        raise StoreDamagedError(
            f"{exc}; nothing was changed; {store_files.recovery_hint(db_path, backup_dir)}"
        ) from exc
    checked_s = time.perf_counter() - started
    try:
        store_files.write_marker(db_path)
        report = store.recover()
    except BaseException:
        store.close()
        raise
    pruned = store.prune_events(settings.store.event_retention_days * 86400.0)
    _log.info(
        "store opened",
        path=str(settings.store.db_path),
        schema_version=store.schema_version(),
        interrupted_targets=report.interrupted_targets,
        queued_targets=report.queued_targets,
        failed_jobs=report.failed_jobs,
        pruned_events=pruned,
        quick_check_s=round(checked_s, 3),
    )
    return store


# ----------------------------------------------------------------------------------- middleware


class _BodyTooLarge(Exception):
    pass


class _ResponseWatch:
    """Passes an app's messages on to ``send`` and notes whether its response has started: once it
    has, an error can no longer be answered with a response of its own."""

    __slots__ = ("_send", "started")

    def __init__(self, send: Send) -> None:
        self._send = send
        self.started = False

    async def send(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            self.started = True
        await self._send(message)


class BodyLimitMiddleware:
    """Refuse request bodies over ``limit_bytes`` with 413, by Content-Length or while streaming."""

    def __init__(self, app: ASGIApp, limit_bytes: int) -> None:
        self.app = app
        self.limit = limit_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.limit or declared < 0:
                    await _send_error(send, 413 if declared > 0 else 400, self._message(declared))
                    return
        received = 0
        response = _ResponseWatch(send)

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise _BodyTooLarge
            return message

        try:
            await self.app(scope, limited_receive, response.send)
        except _BodyTooLarge:
            if not response.started:
                await _send_error(send, 413, self._message(received))

    def _message(self, size: int) -> tuple[str, str]:
        if size < 0:
            return ("bad_request", "invalid Content-Length")
        return (
            "too_large",
            f"request body of {size} bytes is over the limit of {self.limit} bytes (http.max_upload_bytes)",
        )


class InternalErrorMiddleware:
    """Answer any unhandled exception with a generic 500 carrying an error id; log the details."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        response = _ResponseWatch(send)
        try:
            await self.app(scope, receive, response.send)
        except ClientDisconnect:  # nobody to answer; not a fault of ours
            _log.info("client went away during its request", path=scope.get("path"))
        except Exception:
            error_id = uuid.uuid4().hex[:12]
            metrics.HTTP_ERRORS.inc()
            _log.exception(
                "internal error", error_id=error_id, path=scope.get("path"), method=scope.get("method")
            )
            if not response.started:
                await _send_error(send, 500, ("internal", "internal error"), error_id=error_id)


async def _send_error(send: Send, status: int, code_message: tuple[str, str], **extra: Any) -> None:
    response = JSONResponse(
        {"error": code_message[0], "message": code_message[1], **extra}, status_code=status
    )
    body = response.body
    await send({"type": "http.response.start", "status": status, "headers": response.raw_headers})
    await send({"type": "http.response.body", "body": body})


# ------------------------------------------------------------------------------- error handlers


def _error(status: int, code: str, message: str, **extra: Any) -> JSONResponse:
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    body = {"error": code, "message": message, **{k: v for k, v in extra.items() if v is not None}}
    return JSONResponse(body, status_code=status, headers=headers)


#: Store refusals answered with their message alone: exception -> (HTTP status, error code).
_STORE_REFUSALS: dict[type[Exception], tuple[int, str]] = {
    NotFoundError: (404, "not_found"),
    IdempotencyConflict: (409, "idempotency_conflict"),
    ConflictError: (409, "conflict"),
}


def _refusal(status: int, code: str) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
    async def handler(request: Request, exc: Exception) -> JSONResponse:
        return _error(status, code, str(exc))

    return handler


def validation_place(loc: Sequence[str]) -> tuple[int | None, str | None, str | None]:
    """Where a request validation error's ``loc`` points, as (row, column, row label) for the error
    body: a target's or a grating pose's row (1-based) and its field (``a1``.. for a pose's value
    by its index); a query, header or path parameter's name, or a body field's (``body.ridge``), as
    the column; else nothing."""
    if len(loc) >= 3 and list(loc[:2]) in (["body", "targets"], ["body", "poses"]):
        if not loc[2].isdigit():
            return None, None, None
        row, row_label = int(loc[2]) + 1, loc[1][:-1]  # target, pose
        column = None
        if len(loc) > 3:  # a target's field; a pose's value by its index
            column = loc[3] if loc[1] == "targets" else f"a{int(loc[3]) + 1}"
        return row, column, row_label
    if loc and loc[0] in ("query", "header", "path", "body") and len(loc) > 1:
        return None, str(loc[1]), None
    return None, None, None


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError) -> JSONResponse:
        response = _error(exc.status, exc.code, exc.message, **exc.extra)
        retry_after = exc.extra.get("retry_after_s")
        if retry_after is not None:
            response.headers["Retry-After"] = str(retry_after)
        return response

    @app.exception_handler(AuthError)
    async def auth_error(request: Request, exc: AuthError) -> JSONResponse:
        return _error(exc.status, "unauthorized" if exc.status == 401 else "forbidden", exc.message)

    for error, (status, code) in _STORE_REFUSALS.items():
        app.add_exception_handler(error, _refusal(status, code))

    @app.exception_handler(StoreFullError)
    async def storage_full(request: Request, exc: StoreFullError) -> JSONResponse:
        _log.error("store: disk full, request refused", path=exc.path, free_bytes=exc.free_bytes)
        details = [{"path": exc.path, "free_bytes": exc.free_bytes}]
        return _error(507, "insufficient_storage", str(exc), details=details)

    @app.exception_handler(DatasetError)
    async def dataset_error(request: Request, exc: DatasetError) -> JSONResponse:
        return _error(
            422,
            "invalid_dataset",
            str(exc),
            row=exc.row,
            column=exc.column,
            row_label=exc.row_label,
            path=exc.path,
        )

    @app.exception_handler(RequestValidationError)
    async def validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        locs = [[str(p) for p in err.get("loc", ())] for err in errors]
        details: list[dict[str, Any]] = [
            {"loc": loc, "message": str(err.get("msg", "invalid"))}
            for loc, err in zip(locs, errors, strict=True)
        ]
        first_loc = locs[0] if locs else []
        first_message = str(details[0]["message"]) if details else "invalid request"
        where = ".".join(first_loc)
        row, column, row_label = validation_place(first_loc)
        return _error(
            422,
            "invalid_request",
            f"{where}: {first_message}" if where else first_message,
            row=row,
            column=column,
            row_label=row_label,
            details=details,
        )

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        codes = {404: "not_found", 405: "method_not_allowed", 400: "bad_request", 413: "too_large"}
        response = _error(exc.status_code, codes.get(exc.status_code, "http_error"), str(exc.detail))
        if exc.headers:
            response.headers.update(exc.headers)
        if exc.status_code == 405:  # Starlette names the first matching route's methods only
            response.headers["Allow"] = ", ".join(_allowed_methods(request))
        return response


def _allowed_methods(request: Request) -> list[str]:
    """Every method some route of the app takes on the request's path (for a 405's ``Allow``)."""
    methods: set[str] = set()
    for route in request.app.router.routes:
        if isinstance(route, APIRoute) and route.path_regex.match(request.url.path):
            methods |= route.methods or set()
    order = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")
    return sorted(methods, key=lambda m: (order.index(m) if m in order else len(order), m))


# ------------------------------------------------------------------------------- the OpenAPI

_HTTP_METHODS = frozenset({"get", "put", "post", "delete", "patch", "head", "options", "trace"})
_COMMON_ANSWERS: tuple[tuple[str, int, str], ...] = (
    ("security", 401, "no token, an unknown token or a malformed Authorization header"),
    ("security", 403, "the token's role is too low for this operation"),
    ("requestBody", 400, "invalid Content-Length"),
    ("requestBody", 413, "request body over http.max_upload_bytes"),
    ("requestBody", 507, "the disk that holds the store is full; details name the file and the free bytes"),
    ("", 500, "internal error; error_id names the log record"),
)


def _document_common_answers(app: FastAPI) -> None:
    """Add to the OpenAPI description the answers that come from authentication and middleware
    rather than from one route: 401/403 where a token is asked for, 400/413 where a body is taken,
    500 everywhere."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()
        error = {"$ref": "#/components/schemas/ErrorOut"}
        has_error_model = "ErrorOut" in schema.get("components", {}).get("schemas", {})
        for path_item in schema.get("paths", {}).values():
            for method, operation in path_item.items():
                if method not in _HTTP_METHODS:
                    continue
                responses = operation.setdefault("responses", {})
                for needs, status, description in _COMMON_ANSWERS:
                    if needs and needs not in operation:
                        continue
                    answer: dict[str, Any] = {"description": description}
                    if has_error_model:
                        answer["content"] = {"application/json": {"schema": error}}
                    responses.setdefault(str(status), answer)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _document_axis_limits(app: FastAPI, limits_deg: Any) -> None:
    """Put the configured robot's axis limits (deg) into the OpenAPI description of the bodies that
    take axis values (a target's ``a1..a6``, a calibration pose), as the server checks them."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        fresh = app.openapi_schema is None
        schema = build()
        if not fresh:
            return schema
        bounds = [{"minimum": float(lo), "maximum": float(hi)} for lo, hi in limits_deg]
        models = schema.get("components", {}).get("schemas", {})
        target = models.get("TargetIn", {}).get("properties", {})
        for name, bound in zip(AXIS_COLUMNS, bounds, strict=True):
            if name in target:
                target[name].update(bound)
        poses = models.get("GratingCalibrationIn", {}).get("properties", {}).get("poses", {})
        for form in poses.get("anyOf", [poses]):
            if form.get("type") == "array" and isinstance(form.get("items"), dict):
                form["items"]["prefixItems"] = [{"type": "number", **b} for b in bounds]
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


# ------------------------------------------------------------------------------------- the app


def _forward_store_events(state: ServiceState, board: StatusBoard) -> Any:
    bus = state.bus

    def listener(event: EventRecord) -> None:
        board.changed()
        data = {"id": event.id, "target_id": event.target_id, "job_id": event.job_id, **event.message}
        bus.publish(event.kind, data)
        if event.kind.startswith("target."):
            final = event.kind.removeprefix("target.")
            if final in TARGET_FINAL_STATES:
                metrics.TARGETS_FINISHED.labels(state=final).inc()

    return listener


def _lifespan(
    state: ServiceState, board: StatusBoard, uploads: UploadChecker, listener: Any
) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The service's start (the event bus on the loop, store events forwarded, the job runner, the
    status snapshots) and its stop in the reverse order: snapshots, bus, jobs drained then their
    pool, the upload pool, the store's listener."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state.bus.bind_loop(asyncio.get_running_loop())
        state.store.add_listener(listener)
        metrics.set_queue_depth_source(state.store.queue_depth)
        state.runner.start()
        status_task = asyncio.create_task(board.run(), name="status snapshot")
        _log.info("http service started", robot=state.robot.name, job_kinds=state.runner.kinds())
        try:
            yield
        finally:
            await board.stop(status_task)
            state.bus.close()
            await state.runner.drain()
            await asyncio.to_thread(state.runner.shutdown)
            uploads.shutdown()
            state.store.remove_listener(listener)
            metrics.set_queue_depth_source(None)
            _log.info("http service stopped")

    return lifespan


def create_app(
    settings: Settings,
    store: Store,
    daemon_view: DaemonView | None = None,
    *,
    bus: EventBus | None = None,
    job_kinds: Sequence[JobKind] | None = None,
) -> FastAPI:
    """The FastAPI application over ``store``.

    ``daemon_view`` is the running daemon (see :class:`DaemonView`); without one the service says the
    loop is not running. ``bus`` is the event bus the daemon publishes to (one is made if omitted;
    it is ``app.state.svc.bus``). ``job_kinds`` replaces the default job kinds (fit, diagnosis).
    The process pool starts and stops with the app's lifespan.
    """
    from comp_daemon.service import job_kinds as default_kinds
    from comp_daemon.service.routes import datasets, diagnoses, fits, system, target_files, targets

    robot = load_robot(settings.robot.name)
    state = ServiceState(
        settings=settings,
        store=store,
        daemon=daemon_view if daemon_view is not None else DetachedDaemonView(),
        bus=bus if bus is not None else EventBus(settings.http.sse_queue_events),
        tokens=TokenTable(settings.auth),
        runner=JobRunner(store, settings.jobs),
        robot=robot,
    )
    for kind in job_kinds if job_kinds is not None else default_kinds.default_job_kinds():
        state.runner.register(kind)
    uploads = UploadChecker(settings.http.max_concurrent_uploads, settings.http.max_upload_bytes_in_flight)
    board = StatusBoard(state, settings.http.status_interval_s)
    listener = _forward_store_events(state, board)

    app = FastAPI(
        title="comp-daemon",
        version=__version__,
        description=(
            "Accuracy compensation for a robotic drilling cell: data sets, model fits, the MES target "
            "queue, diagnosis reports and the live state of the closed loop. Authenticate with "
            "`Authorization: Bearer <token>`; roles viewer < operator < engineer."
        ),
        lifespan=_lifespan(state, board, uploads, listener),
        docs_url=None,  # Swagger UI and ReDoc load their scripts from a CDN; the cell is offline
        redoc_url=None,
    )
    app.state.svc = state
    app.state.tokens = state.tokens
    app.state.uploads = uploads
    app.state.status = board
    _install_error_handlers(app)
    _document_common_answers(app)
    _document_axis_limits(app, robot.axis_limits_deg)
    app.add_middleware(
        BodyLimitMiddleware, limit_bytes=settings.http.max_upload_bytes + _MULTIPART_OVERHEAD_BYTES
    )
    app.add_middleware(InternalErrorMiddleware)

    app.include_router(system.router)
    app.include_router(datasets.router, prefix="/api")
    app.include_router(fits.router, prefix="/api")
    app.include_router(diagnoses.router, prefix="/api")
    app.include_router(targets.router, prefix="/api")
    app.include_router(target_files.router, prefix="/api")

    @app.get("/", include_in_schema=False)
    async def root() -> RedirectResponse:
        return RedirectResponse("/dashboard/")

    with contextlib.suppress(RuntimeError):  # no static folder in a stripped install
        app.mount("/dashboard", StaticFiles(directory=STATIC_DIR, html=True), name="dashboard")
    return app
