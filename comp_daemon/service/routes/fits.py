"""Fits (jobs that make models), jobs in general, and models: list, compare, activate.

``GET /api/fits/kinds`` lists the model kinds of the registry (:mod:`comp_daemon.models.registry`)
a fit can name. A fit runs in the process pool; ``GET /api/jobs/{id}`` follows it (state,
progress 0..1, result statistics). When it is done, the model it made is listed under
``/api/models`` (inactive); activating one makes the daemon compensate with it from its next
target on. ``GET /api/models/{id}/export?format=kuka|abb|csv`` lists a kinematic model's identified
parameters (``docs/export.md``).
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Query
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import Field

from comp_daemon.common.logs import get_logger
from comp_daemon.export.formats import params_text
from comp_daemon.export.params import listing_of
from comp_daemon.models.artifact import ModelArtifactError, parse_model
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.models.registry import KINDS, UnknownModelError, parse_model_name, with_order
from comp_daemon.service import job_kinds
from comp_daemon.service.routes.params import Engineer, Paging, State, Viewer
from comp_daemon.service.schemas import MAX_ID, ErrorOut, FitIn, JobOut, ModelOut, json_array
from comp_daemon.service.state import ApiError, ServiceState
from comp_daemon.service.store import JobRecord

router = APIRouter()
_log = get_logger("comp_daemon.api.fits")

JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="job id")]
ModelId = Annotated[int, Path(ge=1, le=MAX_ID, description="model id")]

_NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": ErrorOut}}


async def launch_job(
    svc: ServiceState,
    kind: str,
    params: dict[str, Any],
    dataset_id: int,
    make_args: Any,
    *,
    parsed: bool = False,
) -> JobRecord:
    """Create the job row and hand it to the pool; ``make_args(data)`` builds the function's args
    from the stored CSV text, or, with ``parsed``, from the data set as parsed at its upload when
    the service still holds it (:class:`comp_daemon.service.uploads.ParsedDatasets`)."""
    if not svc.runner.has_kind(kind):
        raise ApiError(503, "unavailable", f"{kind} jobs are not available in this service")
    data: Any = None
    if parsed:  # the stored hash picks the parsed data set; the text is not read
        record = await svc.run(svc.store.get_dataset, dataset_id, with_content=False)
        data = svc.parsed.get(dataset_id, record.sha256)
    if data is None:
        data = (await svc.run(svc.store.get_dataset, dataset_id, with_content=True)).content or ""
    job = await svc.run(
        svc.store.create_job, kind, params, dataset_id=dataset_id, max_pending=svc.settings.jobs.max_pending
    )
    try:
        await svc.run(svc.runner.launch, job, make_args(data))
    except Exception:
        await svc.run(svc.store.fail_job, job.id, "could not be started (the job pool is not running)")
        raise
    return job


@router.post(
    "/fits",
    status_code=202,
    response_model=JobOut,
    tags=["fits"],
    summary="Start a fit of a model to a data set (engineer)",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
async def start_fit(body: FitIn, svc: State, who: Engineer) -> JobOut:
    try:
        with_order(parse_model_name(body.model), body.order)
    except UnknownModelError as exc:
        raise ApiError(422, "invalid_request", str(exc), column="model") from None
    settings = body.settings()
    params = {
        "model": body.model,
        "order": body.order,
        **settings.model_dump(mode="json"),
        "dataset_id": body.dataset_id,
        "by": who.name,
    }
    robot_name = svc.settings.robot.name
    job = await launch_job(
        svc,
        job_kinds.FIT,
        params,
        body.dataset_id,
        lambda data: job_kinds.fit_job_args(
            data, robot_name, body.model, body.order, body.dataset_id, settings
        ),
        parsed=True,
    )
    _log.info("fit queued", job_id=job.id, model=body.model, order=body.order, by=who.name)
    return JobOut.of(job)


@router.get("/fits/kinds", tags=["fits"], summary="The model kinds a fit can name")
async def fit_kinds(who: Viewer) -> list[dict[str, Any]]:
    return [
        {
            "name": k.name,
            "summary": k.summary,
            "artifact_kind": k.model_class.kind,
            "effects": k.takes_effects,
            "order": k.takes_order,
            "options": k.takes_options,
            "needs": list(k.needs),
            "uses": list(k.uses),
        }
        for k in KINDS.values()
    ]


@router.get(
    "/jobs",
    response_model=list[JobOut],
    tags=["jobs"],
    summary="List jobs (newest first); results as summaries (per-row errors in GET /api/jobs/{id})",
)
async def list_jobs(
    svc: State,
    who: Viewer,
    page: Paging,
    kind: Annotated[str | None, Query(max_length=32)] = None,
    state: Literal["queued", "running", "done", "failed", "cancelled"] | None = None,
) -> Response:
    rows = await svc.run(
        svc.store.list_jobs,
        kind=kind,
        state=state,
        limit=page.limit,
        offset=page.offset,
        summary=True,
    )
    return json_array(JobOut.of(r, with_result=r.kind != job_kinds.DIAGNOSIS, summary=True) for r in rows)


@router.get("/jobs/{job_id}", response_model=JobOut, tags=["jobs"], summary="One job", responses=_NOT_FOUND)
async def get_job(job_id: JobId, svc: State, who: Viewer) -> JobOut:
    job = await svc.run(svc.store.get_job, job_id)
    return JobOut.of(job, with_result=job.kind != job_kinds.DIAGNOSIS)


@router.post(
    "/jobs/{job_id}/cancel",
    response_model=JobOut,
    tags=["jobs"],
    summary="Cancel a queued or running job (engineer)",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
)
async def cancel_job(job_id: JobId, svc: State, who: Engineer) -> JobOut:
    job = await svc.run(svc.runner.cancel, job_id, by=who.name)
    _log.info("job cancelled", job_id=job_id, by=who.name)
    return JobOut.of(job, with_result=False)


# ---------------------------------------------------------------------------------------- models


@router.get(
    "/models",
    response_model=list[ModelOut],
    tags=["models"],
    summary="List models (newest first); statistics as summaries (per-row errors in GET /api/models/{id})",
)
async def list_models(
    svc: State,
    who: Viewer,
    page: Paging,
) -> Response:
    rows = await svc.run(
        svc.store.list_models,
        limit=page.limit,
        offset=page.offset,
        summary=True,
    )
    return json_array(ModelOut.of(r, summary=True) for r in rows)


@router.get(
    "/models/compare",
    tags=["models"],
    summary="Table 2 of several models side by side (per-axis and 3-D mean/std/max on check rows)",
    responses=_NOT_FOUND,
)
async def compare_models(
    svc: State,
    who: Viewer,
    ids: Annotated[
        list[Annotated[int, Field(ge=1, le=MAX_ID)]],
        Query(min_length=1, max_length=20, description="model ids"),
    ],
) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    baselines: dict[str, Any] = {}
    for model_id in ids:
        model = await svc.run(svc.store.get_model, model_id)
        table = model.stats.get("table2", {})
        rows.append(
            {
                "model_id": model.id,
                "kind": model.kind,
                "order": model.order,
                "active": model.active,
                "dataset_id": model.dataset_id,
                "table2": table.get("model"),
                "errors_3d_mm": model.stats.get("errors_3d_mm", {}).get("model"),
            }
        )
        if model.dataset_id is not None and table.get("nominal") is not None:
            baselines.setdefault(
                str(model.dataset_id),
                {
                    "table2": table.get("nominal"),
                    "errors_3d_mm": model.stats.get("errors_3d_mm", {}).get("nominal"),
                },
            )
    return {"models": rows, "nominal_by_dataset": baselines}


@router.get(
    "/models/active", response_model=ModelOut | None, tags=["models"], summary="The active model, if any"
)
async def active_model(svc: State, who: Viewer) -> ModelOut | None:
    model = await svc.run(svc.store.active_model, with_artifact=False)
    return ModelOut.of(model) if model is not None else None


@router.get(
    "/models/{model_id}", response_model=ModelOut, tags=["models"], summary="One model", responses=_NOT_FOUND
)
async def get_model(model_id: ModelId, svc: State, who: Viewer) -> ModelOut:
    return ModelOut.of(await svc.run(svc.store.get_model, model_id))


@router.get(
    "/models/{model_id}/artifact",
    tags=["models"],
    summary="The model artifact (JSON), as written by comp-daemon fit",
    responses=_NOT_FOUND,
)
async def get_artifact(model_id: ModelId, svc: State, who: Viewer) -> JSONResponse:
    model = await svc.run(svc.store.get_model, model_id, with_artifact=True)
    return JSONResponse(
        model.artifact,
        headers={"Content-Disposition": f'attachment; filename="model-{model.id}-{model.kind}.json"'},
    )


@router.get(
    "/models/{model_id}/export",
    tags=["models"],
    summary="A kinematic model's identified parameters as a KUKA, ABB or CSV listing (docs/export.md)",
    response_class=Response,  # errors are JSON (ErrorOut), the listing text
    responses={
        200: {
            "content": {
                "text/plain": {"schema": {"type": "string"}},
                "text/csv": {"schema": {"type": "string"}},
            },
            "description": "the listing",
        },
        **_NOT_FOUND,
        409: {"model": ErrorOut},
    },
)
async def export_model(
    model_id: ModelId,
    svc: State,
    who: Viewer,
    fmt: Annotated[
        Literal["kuka", "abb", "csv"], Query(alias="format", description="listing format")
    ] = "csv",
) -> Response:
    model = await svc.run(svc.store.get_model, model_id, with_artifact=True)

    def listing() -> str:
        loaded = parse_model(json.dumps(model.artifact), source=f"model {model_id}")
        listed = listing_of(loaded.model, loaded.document)  # ValueError: not a kinematic model
        assert isinstance(loaded.model, KinematicModel)
        return params_text(listed, loaded.model, fmt)[0]

    try:
        text = await svc.run(listing)
    except (ModelArtifactError, ValueError) as exc:
        raise ApiError(409, "conflict", f"model {model_id}: {exc}") from None
    suffix = {"kuka": "dat", "abb": "cfg", "csv": "csv"}[fmt]
    return PlainTextResponse(
        text,
        media_type="text/csv" if fmt == "csv" else "text/plain",
        headers={"Content-Disposition": f'attachment; filename="model-{model_id}-{fmt}.{suffix}"'},
    )


@router.post(
    "/models/{model_id}/activate",
    response_model=ModelOut,
    tags=["models"],
    summary="Make this the model the daemon compensates with (engineer)",
    responses=_NOT_FOUND,
)
async def activate_model(model_id: ModelId, svc: State, who: Engineer) -> ModelOut:
    model = await svc.run(svc.store.activate_model, model_id, by=who.name)
    _log.info("model activated", model_id=model_id, by=who.name)
    return ModelOut.of(model)
