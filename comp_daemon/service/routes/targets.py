"""The MES target queue: post a batch of drilling points once, follow each target, cancel, requeue.

``POST /api/batches`` needs an ``Idempotency-Key`` header. The first request with a key queues
the batch (201); the same key with the same body returns that batch (200) without queueing
anything again; the same key with another body is refused (409). Bodies are compared after
validation (same targets, same values: same body, whatever the spacing or key order).

Each target is validated like a row of a target file (``docs/data-format.md``), in exactly one
form (axis values ``a1..a6`` within the robot's limits, or a wanted TCP ``tx, ty, tz`` with an
optional orientation), JSON numbers only. Then the robot must reach it: a TCP may not lie inside
the robot's base and needs a nominal inverse-kinematics solution inside the axis limits, and a
target whose orientation is held may not lie near the wrist singularity
(``[compensation] wrist_singularity_deg``). A refused batch (422) names the target (1-based), the
field and the reason, and nothing of it is queued. The compensation itself (and its limits on the
axis changes and the model's region) runs when the target executes; from then on the target's
output names the model that compensated it (``model_id``) and, for a model with an uncertainty,
``predicted_sigma_mm``: the 3-D 1-σ uncertainty of the model's predicted TCP at the commanded
axes (from the target's ``target.moving`` event in the store).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Header, Path, Query, Response

from comp_daemon.common.logs import get_logger
from comp_daemon.data.dataset import DatasetError, dataset_from_records
from comp_daemon.data.target import Target
from comp_daemon.kinematics.inverse import UnreachableTargetError
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc
from comp_daemon.models.compensation import (
    CompensationLimits,
    base_refusals,
    nominal_solution,
    wrist_refusals,
)
from comp_daemon.robot.description import RobotDescription
from comp_daemon.service.auth import Principal
from comp_daemon.service.routes.params import Operator, Paging, State, Viewer
from comp_daemon.service.schemas import (
    MAX_ID,
    TARGET_MOVING,
    BatchIn,
    BatchOut,
    ErrorOut,
    TargetOut,
    json_array,
)
from comp_daemon.service.state import ApiError, ServiceState
from comp_daemon.service.store import Store, TargetRecord

router = APIRouter(tags=["targets"])
_log = get_logger("comp_daemon.api.targets")

TargetId = Annotated[int, Path(ge=1, le=MAX_ID, description="target id")]
BatchId = Annotated[int, Path(ge=1, le=MAX_ID, description="batch id")]
TargetState = Literal[
    "queued", "compensating", "moving", "settling", "done", "failed", "cancelled", "interrupted"
]

IdempotencyKey = Annotated[
    str,
    Header(
        alias="Idempotency-Key",
        min_length=1,
        max_length=200,
        pattern=r"^[\x21-\x7e]+$",
        description="the MES's unique key for this batch (printable ASCII, no spaces)",
    ),
]

_CHANGE_ERRORS: dict[int | str, dict[str, Any]] = {404: {"model": ErrorOut}, 409: {"model": ErrorOut}}


def validate_targets(targets: Sequence[Target], robot: RobotDescription, limits: CompensationLimits) -> None:
    """Check every target as a target-file record, then that the robot reaches it (module docstring);
    raise ``DatasetError`` naming the first target at fault (1-based), the field and the problem."""
    _check_records([t.to_record() for t in targets], robot.axis_limits_deg)
    problems: list[tuple[int, str, str]] = []  # (index, field, problem)
    axes = [i for i, t in enumerate(targets) if t.axes_deg is not None]
    if axes:
        a = np.array([targets[i].axes_deg for i in axes], dtype=float)
        problems += [(axes[r.index], "a5", r.reason) for r in wrist_refusals(robot, a, limits)]
    for oriented in (False, True):
        rows = [
            i for i, t in enumerate(targets) if t.tcp_mm is not None and (t.abc_deg is not None) is oriented
        ]
        if rows:
            problems += _reach_problems(targets, rows, oriented, robot, limits)
    if problems:
        index, field, problem = min(problems)
        raise DatasetError(problem, source="batch", row=index + 1, column=field, row_label="target")


def _reach_problems(
    targets: Sequence[Target],
    rows: list[int],
    oriented: bool,
    robot: RobotDescription,
    limits: CompensationLimits,
) -> list[tuple[int, str, str]]:
    """TCP targets: outside the robot's base, a nominal solution inside the axis limits, not near the
    wrist singularity."""
    p = np.array([targets[i].tcp_mm for i in rows], dtype=float)
    inside = base_refusals(robot, p)
    if inside:
        return [(rows[r.index], "tx", r.reason) for r in inside]
    rot = None
    if oriented:
        rot = flange_rotation_of_tool_abc(np.array([targets[i].abc_deg for i in rows], dtype=float))
    try:
        a = nominal_solution(robot, p, rot)
    except UnreachableTargetError as exc:
        return [
            (
                rows[int(i)],
                "tx",
                f"the robot cannot reach this TCP within its axis limits (nominal inverse kinematics "
                f"{float(e):.3f} mm short)",
            )
            for i, e in zip(exc.indices, exc.position_error_mm, strict=True)
        ]
    if not oriented:
        return []
    return [(rows[r.index], "ta", r.reason) for r in wrist_refusals(robot, a, limits)]


def _check_records(records: Sequence[dict[str, Any]], limits_deg: Any) -> None:
    """Check every target as a target-file record; raise ``DatasetError`` naming target and field."""
    groups: dict[tuple[str, ...], list[int]] = {}
    for i, record in enumerate(records):
        groups.setdefault(tuple(sorted(record)), []).append(i)
    first: DatasetError | None = None
    first_index = len(records)
    for indices in groups.values():
        try:
            dataset_from_records(
                [records[i] for i in indices],
                source="batch",
                limits_deg=limits_deg,
                min_rows=1,
                kind="targets",
            )
        except DatasetError as exc:
            index = (
                indices[exc.row - 1] if exc.row is not None and 0 < exc.row <= len(indices) else indices[0]
            )
            if index < first_index:
                first_index = index
                first = DatasetError(
                    exc.problem, source="batch", row=index + 1, column=exc.column, row_label="target"
                )
    if first is not None:
        raise first


def compensations(store: Store, targets: Sequence[TargetRecord]) -> dict[int, dict[str, Any]]:
    """The compensation in the latest :data:`TARGET_MOVING` event of each target with commanded axes
    (a requeued target is compensated again; its earlier compensation no longer counts)."""
    out: dict[int, dict[str, Any]] = {}
    for t in targets:
        if t.commanded_axes_deg is None:
            continue
        for event in store.list_events(target_id=t.id, newest_first=True, limit=50):
            if event.kind == TARGET_MOVING and isinstance(event.message.get("compensation"), dict):
                out[t.id] = event.message["compensation"]
                break
    return out


def _out(store: Store, targets: Sequence[TargetRecord]) -> list[TargetOut]:
    found = compensations(store, targets)
    return [TargetOut.of(t, found.get(t.id)) for t in targets]


def request_sha256(records: Sequence[dict[str, Any]]) -> str:
    canonical = json.dumps(list(records), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


def check_batch_size(svc: ServiceState, size: int, **where: Any) -> None:
    """Refuse (422) a batch of ``size`` targets over ``http.max_batch_targets``; ``where`` names the
    field at fault in the error's body."""
    limit = svc.settings.http.max_batch_targets
    if size > limit:
        raise ApiError(
            422,
            "invalid_request",
            f"batch of {size} targets is over the limit of {limit} (http.max_batch_targets)",
            **where,
        )


async def queue_batch(
    svc: ServiceState,
    response: Response,
    who: Principal,
    idempotency_key: str,
    records: list[dict[str, Any]],
    event: str,
    **logged: Any,
) -> BatchOut:
    """Queue checked target ``records`` as a batch once per ``idempotency_key``: the new batch (201),
    or the one queued earlier under that key (200; a key used with other records is refused 409)."""
    batch, queued, created = await svc.run(
        svc.store.submit_batch, idempotency_key, request_sha256(records), records, source=who.name
    )
    if created:
        _log.info(event, batch_id=batch.id, size=batch.size, **logged, by=who.name)
    else:
        response.status_code = 200
    return BatchOut.of(batch, queued, await svc.run(compensations, svc.store, queued))


@router.post(
    "/batches",
    status_code=201,
    response_model=BatchOut,
    summary="Queue a batch of targets once per Idempotency-Key (operator)",
    responses={
        200: {"model": BatchOut, "description": "the batch queued earlier under this key"},
        409: {"model": ErrorOut, "description": "the key was used with another body"},
        422: {"model": ErrorOut, "description": "a target is refused; row = target number, column = field"},
    },
)
async def post_batch(
    body: BatchIn,
    response: Response,
    svc: State,
    who: Operator,
    idempotency_key: IdempotencyKey,
) -> BatchOut:
    check_batch_size(svc, len(body.targets), column="targets")
    targets = [t.target() for t in body.targets]
    await svc.run(validate_targets, targets, svc.robot, svc.settings.compensation.limits())
    records = [t.to_record() for t in targets]
    return await queue_batch(svc, response, who, idempotency_key, records, "batch queued")


@router.get(
    "/batches/{batch_id:int}",
    response_model=BatchOut,
    summary="A batch and its targets",
    responses=_CHANGE_ERRORS,
)
async def get_batch(batch_id: BatchId, svc: State, who: Viewer) -> BatchOut:
    batch, targets = await svc.run(svc.store.get_batch, batch_id)
    return BatchOut.of(batch, targets, await svc.run(compensations, svc.store, targets))


@router.post(
    "/batches/{batch_id:int}/cancel",
    response_model=list[TargetOut],
    summary="Cancel every queued target of a batch (operator); returns those cancelled",
    responses=_CHANGE_ERRORS,
)
async def cancel_batch(batch_id: BatchId, svc: State, who: Operator) -> list[TargetOut]:
    cancelled = await svc.run(svc.store.cancel_batch, batch_id, by=who.name)
    _log.info("batch cancelled", batch_id=batch_id, cancelled=len(cancelled), by=who.name)
    return await svc.run(_out, svc.store, cancelled)


@router.get("/targets", response_model=list[TargetOut], summary="Targets in queue order (or newest first)")
async def list_targets(
    svc: State,
    who: Viewer,
    page: Paging,
    batch_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    state: Annotated[list[TargetState] | None, Query(description="one or more states")] = None,
    newest_first: bool = False,
) -> Response:
    rows = await svc.run(
        svc.store.list_targets,
        batch_id=batch_id,
        states=state,
        limit=page.limit,
        offset=page.offset,
        newest_first=newest_first,
    )
    return json_array(await svc.run(_out, svc.store, rows))


@router.get("/targets/{target_id}", response_model=TargetOut, summary="One target", responses=_CHANGE_ERRORS)
async def get_target(target_id: TargetId, svc: State, who: Viewer) -> TargetOut:
    target = await svc.run(svc.store.get_target, target_id)
    return (await svc.run(_out, svc.store, [target]))[0]


@router.post(
    "/targets/{target_id}/cancel",
    response_model=TargetOut,
    summary="Cancel a target that has not started, or an interrupted one (operator)",
    responses=_CHANGE_ERRORS,
)
async def cancel_target(target_id: TargetId, svc: State, who: Operator) -> TargetOut:
    target = await svc.run(svc.store.cancel_target, target_id, by=who.name)
    _log.info("target cancelled", target_id=target_id, by=who.name)
    return TargetOut.of(target)


@router.post(
    "/targets/{target_id}/requeue",
    response_model=TargetOut,
    summary="Put an interrupted target back at the end of the queue (operator)",
    responses=_CHANGE_ERRORS,
)
async def requeue_target(target_id: TargetId, svc: State, who: Operator) -> TargetOut:
    target = await svc.run(svc.store.requeue_target, target_id, by=who.name)
    _log.info("target requeued", target_id=target_id, by=who.name)
    return TargetOut.of(target)
