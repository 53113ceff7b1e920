"""Diagnoses of the sim-to-real gap (``docs/diagnosis-output.md``): start one, fetch its reports.

A diagnosis is a job of kind ``diagnosis``; its JSON report is the document of the spec, its HTML
report the pictures. Both are kept with the job.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path
from fastapi.responses import HTMLResponse, Response

from comp_daemon.common.logs import get_logger
from comp_daemon.service import job_kinds
from comp_daemon.service.routes.fits import launch_job
from comp_daemon.service.routes.params import Engineer, Paging, State, Viewer
from comp_daemon.service.schemas import MAX_ID, DiagnosisIn, ErrorOut, JobOut, json_array
from comp_daemon.service.state import ApiError, ServiceState
from comp_daemon.service.store import JobRecord

router = APIRouter(tags=["diagnoses"])
_log = get_logger("comp_daemon.api.diagnoses")

JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="the diagnosis job's id")]

_REPORT_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorOut, "description": "no such diagnosis"},
    409: {"model": ErrorOut, "description": "the diagnosis has not finished (or failed)"},
}
# the report is our own HTML with inline styles and images; nothing else may load or run
_REPORT_CSP = (
    "default-src 'none'; style-src 'unsafe-inline'; img-src data:; base-uri 'none'; form-action 'none'"
)


@router.post(
    "/diagnoses",
    status_code=202,
    response_model=JobOut,
    summary="Start a diagnosis of a data set (engineer)",
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}, 503: {"model": ErrorOut}},
)
async def start_diagnosis(body: DiagnosisIn, svc: State, who: Engineer) -> JobOut:
    robot_name = svc.settings.robot.name
    settings = body.settings()
    job = await launch_job(
        svc,
        job_kinds.DIAGNOSIS,
        {"dataset_id": body.dataset_id, "by": who.name, **settings.model_dump(mode="json")},
        body.dataset_id,
        lambda data: job_kinds.diagnosis_job_args(data, robot_name, body.dataset_id, settings),
        parsed=True,
    )
    _log.info("diagnosis queued", job_id=job.id, dataset_id=body.dataset_id, by=who.name)
    return JobOut.of(job, with_result=False)


@router.get("/diagnoses", response_model=list[JobOut], summary="List diagnoses (newest first)")
async def list_diagnoses(
    svc: State,
    who: Viewer,
    page: Paging,
) -> Response:
    rows = await svc.run(
        svc.store.list_jobs,
        kind=job_kinds.DIAGNOSIS,
        limit=page.limit,
        offset=page.offset,
    )
    return json_array(JobOut.of(r, with_result=False) for r in rows)


async def _finished(svc: ServiceState, job_id: int) -> JobRecord:
    job = await svc.run(svc.store.get_job, job_id)
    if job.kind != job_kinds.DIAGNOSIS:
        raise ApiError(404, "not_found", f"job {job_id} is not a diagnosis")
    if job.state != "done" or job.result is None:
        detail = f": {job.error}" if job.error else ""
        raise ApiError(409, "not_ready", f"diagnosis {job_id} is {job.state}{detail}")
    return job


@router.get(
    "/diagnoses/{job_id}", summary="The JSON report (docs/diagnosis-output.md)", responses=_REPORT_ERRORS
)
async def get_report(job_id: JobId, svc: State, who: Viewer) -> dict[str, Any]:
    job = await _finished(svc, job_id)
    assert job.result is not None
    report: dict[str, Any] = job.result.get("report", {})
    return report


@router.get(
    "/diagnoses/{job_id}/report.html",
    response_class=Response,  # errors are JSON (ErrorOut), the report text/html
    summary="The HTML report",
    responses={200: {"content": {"text/html": {"schema": {"type": "string"}}}}, **_REPORT_ERRORS},
)
async def get_report_html(job_id: JobId, svc: State, who: Viewer) -> HTMLResponse:
    job = await _finished(svc, job_id)
    assert job.result is not None
    html = job.result.get("html")
    if not isinstance(html, str):
        raise ApiError(404, "not_found", f"diagnosis {job_id} has no HTML report")
    return HTMLResponse(
        html, headers={"Content-Security-Policy": _REPORT_CSP, "X-Content-Type-Options": "nosniff"}
    )
