"""The job kinds the service runs in its process pool: ``fit`` and ``diagnosis``.

Worker functions take picklable arguments (the data set as canonical CSV text, or for a fit the
data set as its upload parsed it, :class:`comp_daemon.service.uploads.ParsedDatasets`; the robot's
preset name or path) and return JSON-ready dicts; they never touch the store. Parent-side hooks
turn a fit's result into a stored model.

A fit is the fit pipeline of ``comp-daemon fit`` (:mod:`comp_daemon.preparation.pipeline`) on the
data set's fit rows (the ``split`` column, or a reproducible draw), judged with seed 000's Table 2
(:func:`comp_daemon.models.evaluation.error_statistics`) on the check rows next to the nominal
twin (registered to the data's frame); the model is stored as its artifact document
(:func:`comp_daemon.models.artifact.model_document`), which the daemon loads back bit-exact. Model
names are those of ``comp-daemon fit`` (:func:`comp_daemon.models.registry.parse_model_name`):
every kind of the registry, ``chebyshev:m`` / ``chebyshev:cv``, ``kinematic+ratio+backlash``.

Fit result (``job.result``) and model ``stats``::

    {"model": name, "kind": kind, "artifact_kind": the stored model's kind (kriging-backlash: kriging),
     "effects": [...], "order": m, "frame": "base"|"tracker",
     "rows": {"fit": n, "check": n}, "split": message,
     "directions": null | how the approach directions were inferred from the pose order,
     "table2": {"nominal": T, "model": T}, "errors_3d_mm": {"nominal": [...], "model": [...]},
     "fit": {...fit_model's summary...}}

``T`` is ``error_statistics`` (mm, error = measured − predicted): per axis signed mean/std and max
|component|, 3-D mean/std/max/rms; ``errors_3d_mm`` are the check rows' 3-D errors (the histogram
of seed 000 Fig. 11).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from comp_daemon.preparation.options import DiagnosisSettings, FitSettings
from comp_daemon.service.jobs import JobKind
from comp_daemon.service.store import JobRecord, ModelDraft

if TYPE_CHECKING:
    from comp_daemon.data.table import Dataset
    from comp_daemon.preparation.pipeline import FitOutcome

__all__ = [
    "DIAGNOSIS",
    "FIT",
    "default_job_kinds",
    "diagnosis_job_args",
    "fit_done",
    "fit_job_args",
    "run_diagnosis",
    "run_fit",
]

FIT = "fit"
DIAGNOSIS = "diagnosis"

Progress = Callable[..., None]


# -------------------------------------------------------------------------------------------- fit


def fit_job_args(
    data: str | Dataset,
    robot: str,
    model: str,
    order: int | None,
    dataset_id: int,
    settings: FitSettings | None = None,
) -> tuple[Any, ...]:
    return (data, robot, model, order, dataset_id, settings)


def run_fit(
    data: str | Dataset,
    robot_name: str,
    model: str,
    order: int | None,
    dataset_id: int,
    settings: FitSettings | None = None,
    *,
    progress: Progress,
) -> dict[str, Any]:
    """Fit ``model`` on the fit rows of the data set, judge it and the nominal twin on the check rows.

    ``data`` is the data set as parsed at its upload (:class:`ParsedDatasets`), or its stored
    canonical CSV text, parsed here, when the service no longer holds it. The fit is the pipeline
    ``comp-daemon fit`` runs (:mod:`comp_daemon.preparation.pipeline`) with the same ``settings``
    (:class:`~comp_daemon.preparation.options.FitSettings`; omitted: the defaults), with check rows
    drawn when the file has no split; a data set without ``dir`` columns gets the approach
    directions from the pose order when the model needs them (unless ``infer_dir`` is off), and the
    stats' ``directions`` says so.
    """
    from comp_daemon.data.bars import campaign_kind, read_table, sniff_campaign
    from comp_daemon.models.registry import parse_model_name, with_order
    from comp_daemon.preparation.pipeline import FitRequest, fit_prepared, prepare_fit
    from comp_daemon.robot.description import load_robot

    settings = settings or FitSettings()
    spec = with_order(parse_model_name(model), order)
    robot = load_robot(robot_name)
    progress(0.02, "reading the data set")
    source = f"dataset {dataset_id}"
    if isinstance(data, str) and sniff_campaign(data) is not None:
        table = read_table(data.encode("utf-8"), fmt="csv", source=source, limits_deg=robot.axis_limits_deg)
        return _run_campaign_fit(table, robot, model, settings, progress)
    if not isinstance(data, str) and campaign_kind(data) is not None:
        return _run_campaign_fit(data, robot, model, settings, progress)
    ds = _measurement(data, source, robot)
    request = FitRequest(spec, settings, hold_out=True)
    prepared = prepare_fit(ds, robot, request)
    progress(0.05, f"fitting {spec.name}" + (" (order by cross-validation)" if spec.order_by_cv else ""))
    outcome = fit_prepared(prepared, robot, request)
    progress(0.9, "judging on the check rows")
    return {"stats": _judged(outcome, robot, model), "artifact": outcome.artifact()}


def _judged(outcome: FitOutcome, robot: Any, model: str) -> dict[str, Any]:
    """A fit's statistics (the module docstring's ``stats``): the model and the nominal twin,
    registered on the same fit rows, judged on the check rows by seed 000's Table 2."""
    from comp_daemon.models.evaluation import error_statistics
    from comp_daemon.models.fitting import FitOptions, ModelSpec
    from comp_daemon.models.registry import fit_spec

    prepared, fitted, spec = outcome.prepared, outcome.fitted, outcome.spec
    train = prepared.rows(prepared.fit_rows)
    nominal = fit_spec(ModelSpec("nominal"), robot, train, FitOptions(frame=prepared.frame))
    check = prepared.rows(prepared.check_rows)
    pred_model = fitted.model.predict_tcp_mm(check.a_deg, check.dir, check.payload_kg, check.temp_c)
    pred_nominal = nominal.model.predict_tcp_mm(check.a_deg)
    p_check = check.xyz_mm
    return {
        "model": model,
        "kind": spec.kind,
        "artifact_kind": fitted.model.kind,
        "effects": list(spec.effects),
        "order": fitted.model.order,
        "frame": fitted.frame,
        "rows": {"fit": len(prepared.fit_rows), "check": len(prepared.check_rows)},
        "split": prepared.split.message,
        "directions": prepared.directions.note,
        "table2": {
            "nominal": error_statistics(p_check, pred_nominal),
            "model": error_statistics(p_check, pred_model),
        },
        "errors_3d_mm": {
            "nominal": np.linalg.norm(p_check - pred_nominal, axis=1).round(6).tolist(),
            "model": np.linalg.norm(p_check - pred_model, axis=1).round(6).tolist(),
        },
        "fit": outcome.info,
    }


def _measurement(data: str | Dataset, source: str, robot: Any) -> Dataset:
    """The measurement data set a job works on: as its upload parsed it, or its stored text parsed
    by the upload's rules (the robot's axis limits; a1..a6 and x, y, z required). A kept data set
    without axis values or positions is read from its text too, whose reader says what is missing."""
    from comp_daemon.data.dataset import dataset_to_csv, parse_dataset

    if not isinstance(data, str) and data.a_deg is not None and data.xyz_mm is not None:
        return data
    text = data if isinstance(data, str) else dataset_to_csv(data)
    return parse_dataset(
        text, source=source, limits_deg=robot.axis_limits_deg, min_rows=1, kind="measurement"
    )


def _run_campaign_fit(
    table: Dataset, robot: Any, model: str, settings: FitSettings, progress: Progress
) -> dict[str, Any]:
    """A ballbar campaign calibrates the ``poe`` model, a cross-bar campaign the ``kinematic`` model
    (:func:`comp_daemon.preparation.pipeline.calibrate_campaign`, as ``comp-daemon fit`` does); the
    stats give the rank reached, the directions the instrument cannot see, with a ``split`` the bar
    errors of the check arcs or crosses before and after, and for a ballbar campaign of repeated
    poses its uncertainty report (``uncertainty``, spec A.8)."""
    from comp_daemon.data.bars import campaign_kind
    from comp_daemon.instruments.campaign_fit import uncertainty_summary
    from comp_daemon.preparation.pipeline import calibrate_campaign

    progress(0.05, f"calibrating from the {campaign_kind(table)} campaign")
    outcome = calibrate_campaign(table, robot, model, settings)
    fitted, check, info = outcome.fitted, outcome.check, outcome.info
    stats = {
        "model": model,
        "kind": fitted.model.kind,
        "artifact_kind": fitted.model.kind,
        "effects": [],
        "order": None,
        "frame": fitted.frame,
        "campaign": info["campaign"],
        "rank": info["rank"],
        "not_identifiable": info["not_identifiable"],
        # pairs the instrument barely tells apart: named by correlation and condition
        "near_dependent": info["identifiability"].get("near_dependent", []),
        "near_dependent_fixed": info.get("near_dependent_fixed", []),
        "rows": {"fit": check["fit_rows"], "check": check["check_rows"]},
        "split": "the file's split (whole arcs / placements)"
        if table.split is not None
        else "every row fitted",
        "directions": None,
        "bar_error_rms_mm": check.get("bar_error_rms_mm"),
        "uncertainty": uncertainty_summary(info),
        "fit": info,
    }
    return {"stats": stats, "artifact": outcome.artifact()}


def fit_done(job: JobRecord, result: Mapping[str, Any]) -> ModelDraft:
    stats = dict(result["stats"])
    return ModelDraft(
        kind=str(stats["kind"]),
        order=stats.get("order"),
        artifact=dict(result["artifact"]),
        stats=stats,
        dataset_id=job.dataset_id,
    )


# -------------------------------------------------------------------------------------- diagnosis


def diagnosis_job_args(
    data: str | Dataset, robot: str, dataset_id: int, settings: DiagnosisSettings | None = None
) -> tuple[Any, ...]:
    return (data, robot, dataset_id, settings)


def run_diagnosis(
    data: str | Dataset,
    robot_name: str,
    dataset_id: int,
    settings: DiagnosisSettings | None = None,
    *,
    progress: Progress,
) -> dict[str, Any]:
    """The diagnosis of ``docs/diagnosis-output.md`` on the data set: JSON report and HTML report.

    ``settings`` are those ``comp-daemon diagnose`` takes
    (:class:`~comp_daemon.preparation.options.DiagnosisSettings`; omitted: the method's), e.g. the
    tracker uncertainty the engineer declares (``tracker_sigma_mm``, σ per axis, mm: the noise
    floor when the data have no repeated poses). ``data``: as for :func:`run_fit`.
    """
    from comp_daemon.diagnosis import diagnose
    from comp_daemon.diagnosis.options import diagnose_options
    from comp_daemon.diagnosis.report import render_report_html
    from comp_daemon.robot.description import load_robot

    robot = load_robot(robot_name)
    progress(0.02, "reading the data set")
    ds = _measurement(data, f"dataset {dataset_id}", robot)
    progress(0.05, "diagnosing")
    diagnosis = diagnose(ds, robot, diagnose_options(settings or DiagnosisSettings()))
    progress(0.9, "writing the report")
    return {"report": diagnosis.to_json(), "html": render_report_html(diagnosis)}


def _fit_job_result(result: Mapping[str, Any]) -> dict[str, Any]:
    """What a fit job's row keeps: the statistics (the artifact is kept with the model)."""
    return {"stats": result["stats"]}


def default_job_kinds() -> list[JobKind]:
    """``fit`` (stores a model when done) and ``diagnosis``."""
    return [
        JobKind(FIT, run_fit, on_done=fit_done, job_result=_fit_job_result),
        JobKind(DIAGNOSIS, run_diagnosis, on_done=None),
    ]
