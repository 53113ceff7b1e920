"""Health, readiness, metrics, the status overview, the live event stream, and the loop's operator actions.

Operator actions (answered 409 ``not_ready`` when no daemon is attached): ``POST /api/gratings/calibrate``
(engineer) starts seed 000's grating calibration in the background and answers 202 at once;
``GET /api/gratings`` follows it (``calibrating``, the calibration in use, ``last_error``);
``POST /api/loop/reset-fault`` (operator) acknowledges a latched fault (a stop must also be cleared
on the robot).

``/ready``, ``/api/status`` and the dashboard read one status snapshot with one ready rule
(:mod:`comp_daemon.service.status`). ``GET /api/status`` carries, under ``rsi``, the RSI sessions
of a daemon that tracks them
(:class:`RsiReporter`): each stop with when, why (``late_replies``, ``timeout``, ``fault``,
``operator``), the cycles and late replies before it, and what happens next (the simulated
controller's re-arm, or what the operator must do on the robot); ``null`` without a daemon.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse

from comp_daemon import __version__
from comp_daemon.service import metrics
from comp_daemon.service.auth import Principal, require
from comp_daemon.service.config import Role
from comp_daemon.service.daemon_view import DaemonControl
from comp_daemon.service.events import CLOSING
from comp_daemon.service.routes.params import Engineer, Operator, State, Viewer
from comp_daemon.service.schemas import (
    MAX_ID,
    ErrorOut,
    EventOut,
    GratingCalibrationIn,
    ReadyOut,
    json_array,
)
from comp_daemon.service.state import ApiError, ServiceState
from comp_daemon.service.status import RsiReporter, StatusBoard

__all__ = ["RsiReporter", "router"]

router = APIRouter()

MetricsReader = Annotated[Principal, Depends(require(Role.viewer, anonymous_if="anonymous_metrics"))]


def _board(request: Request) -> StatusBoard:
    board: StatusBoard = request.app.state.status
    return board


Board = Annotated[StatusBoard, Depends(_board)]


@router.get("/health", tags=["system"], summary="Liveness: the process answers")
async def health() -> dict[str, str]:
    return {"status": "ok", "version": __version__}


@router.get(
    "/ready",
    tags=["system"],
    summary="Readiness: loop running, encoders fresh, a model active",
    response_model=ReadyOut,
    responses={503: {"model": ReadyOut, "description": "not ready; the reasons say why"}},
)
async def ready(board: Board) -> JSONResponse:
    reasons = list((await board.current())["reasons"])
    body = ReadyOut(ready=not reasons, reasons=reasons)
    return JSONResponse(body.model_dump(), status_code=200 if not reasons else 503)


@router.get(
    "/metrics",
    tags=["system"],
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}}},
)
async def get_metrics(who: MetricsReader) -> Response:
    body = await asyncio.to_thread(metrics.render)
    return Response(body, media_type=metrics.CONTENT_TYPE_LATEST)


@router.get(
    "/api/status",
    tags=["system"],
    summary="Everything the dashboard shows at a glance (a snapshot at most http.status_interval_s old)",
    response_class=Response,
    responses={200: {"content": {"application/json": {"schema": {"type": "object"}}}}},
)
async def status(board: Board, who: Viewer) -> Response:
    body = await board.current_body()
    you = json.dumps({"name": who.name, "role": who.role.name}).encode()
    return Response(body[:-1] + b',"you":' + you + b"}", media_type="application/json")


@router.get(
    "/api/events",
    tags=["system"],
    summary="Live updates as server-sent events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def events(
    svc: State,
    who: Viewer,
    kinds: Annotated[
        str | None, Query(max_length=500, description="comma-separated kinds or prefixes, e.g. loop,target")
    ] = None,
) -> StreamingResponse:
    wanted = frozenset(k.strip() for k in kinds.split(",") if k.strip()) if kinds else None
    keepalive = svc.settings.http.sse_keepalive_s

    async def stream() -> AsyncIterator[str]:
        sub = svc.bus.subscribe(wanted)  # here, so that a client gone before the first byte leaks nothing
        try:
            hello = {"version": __version__, "daemon": svc.daemon.snapshot().to_dict()}
            yield f"retry: 3000\nevent: hello\ndata: {json.dumps(hello, default=str)}\n\n"
            while True:
                event = await sub.get(timeout=keepalive)
                if event is None:
                    yield ": keepalive\n\n"
                    continue
                yield event.sse(sub.take_dropped())
                if event.kind == CLOSING:
                    return
        finally:
            sub.close()

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
    )


@router.get(
    "/api/events/log", tags=["system"], summary="The persisted event log", response_model=list[EventOut]
)
async def event_log(
    svc: State,
    who: Viewer,
    after_id: Annotated[int, Query(ge=0, le=MAX_ID)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    target_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    job_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    newest_first: bool = False,
) -> Response:
    rows = await svc.run(
        svc.store.list_events,
        after_id=after_id,
        limit=limit,
        target_id=target_id,
        job_id=job_id,
        newest_first=newest_first,
    )
    return json_array(EventOut.of(e) for e in rows)


# ----------------------------------------------------------------------------- operator actions


def _control(svc: ServiceState) -> DaemonControl:
    if not isinstance(svc.daemon, DaemonControl):
        raise ApiError(409, "not_ready", "no real-time daemon is attached to this service")
    return svc.daemon


@router.get(
    "/api/gratings",
    tags=["loop"],
    summary="The grating calibration in use and the state of the last calibration run",
    responses={409: {"model": ErrorOut}},
)
async def grating_status(svc: State, who: Viewer) -> dict[str, Any]:
    return _control(svc).grating_status()


@router.post(
    "/api/gratings/calibrate",
    status_code=202,
    tags=["loop"],
    summary="Start the grating calibration (seed 000 step 1) on the cell (engineer)",
    responses={409: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
async def calibrate_gratings(
    svc: State, who: Engineer, body: GratingCalibrationIn | None = None
) -> dict[str, Any]:
    control = _control(svc)
    poses = None if body is None else body.poses
    if poses is not None:
        limits = svc.robot.axis_limits_deg
        for i, pose in enumerate(poses):
            if len(pose) != 6:
                raise ApiError(
                    422, "invalid_request", f"pose {i + 1}: expected 6 axis values, got {len(pose)}",
                    row=i + 1, row_label="pose",
                )  # fmt: skip
            for j, v in enumerate(pose):
                if not math.isfinite(v) or not limits[j, 0] <= v <= limits[j, 1]:
                    raise ApiError(
                        422,
                        "invalid_request",
                        f"pose {i + 1}: A{j + 1} = {v} deg is outside the axis limits "
                        f"[{limits[j, 0]:g}, {limits[j, 1]:g}]",
                        row=i + 1, column=f"a{j + 1}", row_label="pose",
                    )  # fmt: skip
    try:
        control.start_grating_calibration(poses, who.name)
    except RuntimeError as exc:
        raise ApiError(409, "conflict", str(exc)) from None
    started = {"by": who.name, "poses": None if poses is None else len(poses)}
    await svc.run(svc.store.add_event, "gratings.started", started)
    return control.grating_status()


@router.post(
    "/api/loop/reset-fault",
    tags=["loop"],
    summary="Acknowledge a latched fault of the loop (operator)",
    responses={409: {"model": ErrorOut}},
)
async def reset_fault(svc: State, who: Operator) -> dict[str, Any]:
    control = _control(svc)
    cleared = control.acknowledge_fault(who.name)
    if cleared is not None:
        await svc.run(svc.store.add_event, "loop.fault_reset", {**cleared, "by": who.name})
    return {"cleared": cleared, "daemon": svc.daemon.snapshot().to_dict()}
