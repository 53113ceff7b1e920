"""The one fit pipeline: ``comp-daemon fit`` and the HTTP fit job call it, ``evaluate`` its steps.

A measurement data set, read once, goes through four steps::

    refuse_undetermined   too few rows for the model's parameters, a compliance nothing loads
    prepare_fit           prepare_campaign: directions, split, the row floor (MIN_POSES), frame
    fit_prepared          the registry's fit_spec on the fit rows; a kinematic fit with fewer fit
                          rows than identifiable parameters is refused
    FitOutcome            the fitted model, the fit information an artifact keeps, the artifact

A ballbar or cross-bar campaign (told by :func:`comp_daemon.data.bars.campaign_kind`) takes
:func:`calibrate_campaign` instead: the instrument's own calibration of a ``poe`` or ``kinematic``
model.

Every refusal is a :class:`~comp_daemon.preparation.campaign.CampaignError` (a ``ValueError``)
whose one sentence names the data set: the command line prints it and exits 2, the HTTP job
fails with it, so both say the same words.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.campaigns import campaign_of
from comp_daemon.data.table import Dataset
from comp_daemon.instruments.campaign_fit import fit_campaign
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.artifact import model_document
from comp_daemon.models.fitting import FitOptions, FittedModel, ModelSpec
from comp_daemon.models.registry import fit_spec, undetermined_reason, uses_directions
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG
from comp_daemon.preparation.campaign import (
    CampaignError,
    FrameChoice,
    PreparedCampaign,
    PrepareOptions,
    prepare_campaign,
)
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "CampaignOutcome",
    "FitOutcome",
    "FitRequest",
    "calibrate_campaign",
    "fit_dataset",
    "fit_prepared",
    "fit_rows_checked",
    "nominal_tcp",
    "prepare_fit",
    "prepare_for_models",
    "refuse_undetermined",
]


@dataclass(frozen=True)
class FitRequest:
    """What a door asks of the pipeline.

    ``hold_out``: draw check rows when the file has no ``split`` column (the HTTP job judges on
    them); without it every row is a fit row (``comp-daemon fit``). ``frame``, ``cv_folds`` and
    ``seed`` are the fit's (:class:`~comp_daemon.models.fitting.FitOptions`).
    """

    spec: ModelSpec
    frame: FrameChoice = "auto"
    infer_directions: bool = True
    hold_out: bool = True
    cv_folds: int = 5
    seed: int = 0
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG  # a 6-DOF probe's orientation σ per axis


@dataclass(frozen=True)
class FitOutcome:
    """A fitted model and what the artifact keeps of its fit (``info``)."""

    prepared: PreparedCampaign
    spec: ModelSpec
    fitted: FittedModel
    info: dict[str, Any]

    @property
    def fit_rows(self) -> NDArray[np.int64]:
        return self.prepared.fit_rows

    def artifact(self) -> dict[str, Any]:
        """The model's artifact document (:func:`comp_daemon.models.artifact.model_document`)."""
        return model_document(
            self.fitted.model, data_sha256=self.prepared.data_sha256, frame=self.fitted.frame, fit=self.info
        )


def refuse_undetermined(spec: ModelSpec, robot: RobotDescription, dataset: Dataset) -> None:
    """Refuse a data set whose rows (with the robot description) cannot determine ``spec``
    (:func:`comp_daemon.models.registry.undetermined_reason`)."""
    reason = undetermined_reason(spec, robot, len(dataset), dataset.payload_kg)
    if reason is not None:
        raise CampaignError(f"{dataset.source}: {len(dataset)} data rows; {reason}")


def prepare_for_models(
    dataset: Dataset,
    robot: RobotDescription,
    specs: Sequence[ModelSpec],
    *,
    frame: FrameChoice = "auto",
    infer_directions: bool = True,
    hold_out: bool = True,
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG,
) -> PreparedCampaign:
    """The campaign prepared for these models: directions inferred when one of them needs them,
    check rows drawn and required when ``hold_out``."""
    options = PrepareOptions(
        frame=frame,
        need_directions=any(uses_directions(s) for s in specs),
        infer_directions=infer_directions,
        hold_out=hold_out,
        require_check=hold_out,
        probe_sigma_deg=probe_sigma_deg,
    )
    return prepare_campaign(dataset, robot, options)


def prepare_fit(dataset: Dataset, robot: RobotDescription, request: FitRequest) -> PreparedCampaign:
    """The first two steps: the model's refusal of too few rows, then the preparation."""
    refuse_undetermined(request.spec, robot, dataset)
    return prepare_for_models(
        dataset,
        robot,
        [request.spec],
        frame=request.frame,
        infer_directions=request.infer_directions,
        hold_out=request.hold_out,
        probe_sigma_deg=request.probe_sigma_deg,
    )


def fit_rows_checked(
    prepared: PreparedCampaign,
    spec: ModelSpec,
    robot: RobotDescription,
    options: FitOptions,
    rows: NDArray[np.int64],
) -> FittedModel:
    """``fit_spec`` on the prepared campaign's ``rows``; its refusals (a missing column, an
    undetermined model, a failed solve) as :class:`CampaignError` naming the data set."""
    try:
        return fit_spec(spec, robot, prepared.rows(rows), options)
    except np.linalg.LinAlgError as exc:
        raise CampaignError(f"{prepared.source}: the {spec.name} fit failed ({exc})") from None
    except ValueError as exc:
        raise CampaignError(f"{prepared.source}: {exc}") from None


def fit_prepared(prepared: PreparedCampaign, robot: RobotDescription, request: FitRequest) -> FitOutcome:
    """The fit on the prepared campaign's fit rows, and the information its artifact keeps."""
    spec, rows = request.spec, prepared.fit_rows
    options = FitOptions(frame=prepared.frame, cv_folds=request.cv_folds, seed=request.seed)
    fitted = fit_rows_checked(prepared, spec, robot, options, rows)
    identifiable = fitted.info.get("identifiability", {}).get("identifiable", 0)
    if spec.kind == "kinematic" and len(rows) < identifiable:
        raise CampaignError(
            f"{prepared.source}: {len(rows)} fit rows for {identifiable} identifiable parameters"
        )
    held_out = prepared.dataset.split is not None or len(prepared.check_rows) > 0
    info = {
        **fitted.info,
        "model": spec.name,
        "data_rows_used": "fit rows" if held_out else "all rows",
        "data_source": prepared.source,
    }
    if prepared.directions.note:
        info["directions"] = prepared.directions.note
    return FitOutcome(prepared, spec, fitted, info)


def fit_dataset(dataset: Dataset, robot: RobotDescription, request: FitRequest) -> FitOutcome:
    """The whole pipeline in one call (:func:`prepare_fit`, then :func:`fit_prepared`)."""
    return fit_prepared(prepare_fit(dataset, robot, request), robot, request)


def nominal_tcp(robot: RobotDescription) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """The robot description's TCP (n, 3) of axis values (n, 6): the campaign readers' 5 mm pivot check."""
    params = KinematicParams.from_robot(robot)
    return lambda a_deg: tcp_position_mm(params, axes_deg_to_q_rad(a_deg, params.sign))


@dataclass(frozen=True)
class CampaignOutcome:
    """A ballbar or cross-bar calibration: the fitted model, its check (``campaign_check``), the
    information its artifact keeps and the table's content hash."""

    fitted: FittedModel
    check: dict[str, Any]
    info: dict[str, Any]
    data_sha256: str

    def artifact(self) -> dict[str, Any]:
        return model_document(
            self.fitted.model, data_sha256=self.data_sha256, frame=self.fitted.frame, fit=self.info
        )


def calibrate_campaign(
    table: Dataset,
    robot: RobotDescription,
    model: str,
    *,
    seed: int = 0,
    fix_near_dependent: bool = False,
    ridge: bool = False,
) -> CampaignOutcome:
    """A ballbar campaign calibrates the ``poe`` model, a cross-bar campaign the ``kinematic`` model
    (:func:`comp_daemon.instruments.campaign_fit.fit_campaign`), from the table read with every column;
    refusals as :class:`CampaignError` naming the campaign."""
    try:
        campaign = campaign_of(table, tcp_mm=nominal_tcp(robot))
    except ValueError as exc:
        raise CampaignError(str(exc)) from None
    if campaign is None:
        raise CampaignError(f"{table.source}: neither a ballbar nor a cross-bar campaign")
    try:
        fitted, check = fit_campaign(
            robot, campaign, model=model, seed=seed, fix_near_dependent=fix_near_dependent, ridge=ridge
        )
    except ValueError as exc:
        raise CampaignError(f"{campaign.source}: {exc}") from None
    info = {
        **fitted.info,
        "model": fitted.model.kind,
        "data_source": campaign.source,
        "campaign_check": check,
        "data_rows_used": "fit rows" if campaign.rows.split is not None else "all rows",
    }
    return CampaignOutcome(fitted, check, info, table.content_sha256)
