"""Kinematic models calibrated from ballbar and cross-bar campaigns (seeds 002 and 003).

- :func:`fit_ballbar_campaign`: the ballbar lengths of a campaign (:mod:`comp_daemon.data.ballbar`)
  identify the POE errors Δl, Δθ and the pivot offset (:func:`comp_daemon.instruments.ballbar.fit_ballbar`)
  on the paper's segment layout where the robot is its IRB 120 (Table 1,
  :func:`comp_daemon.models.poe.calibration.paper_layout`), else one segment per joint point;
  the result is a ``poe`` model (:class:`~comp_daemon.models.poe.model.PoeErrorModel`) in the robot
  base frame, carrying the covariance of its identified errors. A campaign whose poses are measured
  repeatedly (``pose_id`` with ≥ 2 repeats each) is fitted in the uncertainty mode of spec A.8
  (:func:`fit_ballbar_repeats`): each pose's last repeat is its reading, the spread of its repeats
  gives the standard uncertainty u and the expanded one b = 1.96·u (95 %), the fit weights each
  reading by 1/max(u, 0.5 µm)², the nested correction re-identifies on corrected readings, and the
  covariance is (JᵀWJ)⁻¹ — the measurement uncertainty, not the residual, scales it, and through
  it the model's prediction σ.
- :func:`fit_crossbar_campaign`: the cross-bar readings (:mod:`comp_daemon.data.crossbar`) identify
  the MDH errors and the probe (tool) offset by the weighted distance and perpendicularity rows
  (:func:`comp_daemon.instruments.crossbar.calibrate_crossbar`); the result is a ``kinematic`` model
  (:class:`~comp_daemon.models.kinematic.KinematicModel`) in the nominal base frame.

Neither instrument sees where the robot stands: a ballbar measures lengths, a cross-bar distances
and angles. Rotations about and shifts along axis 1 (Δθ1, Δl1 + Δl2 for the ballbar; θ1, d1 for the
cross-bar) are kept at zero and reported as not identifiable, together with the other null
directions; the fit summary (``info``) gives the rank reached. On tracker data the base frame of
such a model is registered to the tracker on fit rows (:func:`registered_prediction`), as for the
``nominal`` model, before it predicts check rows.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.data.ballbar import BallbarCampaign
from comp_daemon.data.campaigns import Campaign
from comp_daemon.data.crossbar import CrossbarCampaign
from comp_daemon.estimation.identifiability import IdentifiabilityReport
from comp_daemon.estimation.registration import rigid_registration, transform_points
from comp_daemon.estimation.uncertainty import (
    U_FLOOR_MM,
    Z_95,
    NestedResult,
    covariance_scale,
    nested_identification,
    repeat_uncertainty,
    weights_from_uncertainty,
)
from comp_daemon.instruments.ballbar import (
    BALLBAR_PARAM_NAMES,
    RIDGE_SCALES,
    BallbarFit,
    ballbar_lengths_mm,
    fit_ballbar,
)
from comp_daemon.instruments.crossbar import bar_errors_mm, calibrate_crossbar, check_plan, constraint_rows
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.poe import N_POE_PARAMS, POE_PARAM_NAMES, PoeModel
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.covariance import ParameterCovariance, covariance_from_fit, near_dependent_pairs
from comp_daemon.models.fitting import FittedModel, report_info
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.models.poe.calibration import LAYOUTS, layout_twists, paper_layout
from comp_daemon.models.poe.model import PoeErrorModel
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "CAMPAIGN_MODELS",
    "campaign_model",
    "fit_ballbar_campaign",
    "fit_ballbar_repeats",
    "fit_campaign",
    "fit_crossbar_campaign",
    "registered_prediction",
    "uncertainty_summary",
]

_log = get_logger(__name__)


#: the frame of a model fitted on a campaign: neither instrument sees where the robot stands
_CAMPAIGN_FRAME = "robot base (nominal); a tracker frame is registered on tracker data"


def _campaign_info(
    kind: str,
    *,
    rows: int,
    rms_mm: float,
    rank: int,
    parameters: int,
    solver: dict[str, Any],
    report: IdentifiabilityReport,
    near_dependent: list[dict[str, Any]],
    not_identifiable: list[str],
    identified: dict[str, Any],
) -> dict[str, Any]:
    """The part of a campaign fit's ``info`` both instruments give: the rows fitted and the residual,
    the solver's end, what the rows identify (rank, near-dependent pairs) and what they cannot, the
    values, and the frame; each fit adds its instrument's own entries."""
    return {
        "kind": kind,
        "campaign": kind,
        "rows": rows,
        "rms_mm": rms_mm,
        "rank": rank,
        "parameters": parameters,
        "solver": solver,
        "identifiability": {**report_info(report), "near_dependent": near_dependent},
        "not_identifiable": not_identifiable,
        "identified": identified,
        "frame": _CAMPAIGN_FRAME,
    }


def _identified(
    keep: NDArray[np.intp], values: NDArray[np.float64], std: NDArray[np.float64]
) -> dict[str, Any]:
    """The fitted ballbar parameters ``keep``: value and standard uncertainty of each, by name."""
    return {BALLBAR_PARAM_NAMES[i]: {"value": float(values[i]), "std": float(std[i])} for i in keep}


def _repeat_readings(
    campaign: BallbarCampaign, idx: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.int64]]:
    """Per pose among rows ``idx``: the row of its last repeat, the standard uncertainty u of one
    reading (type A, eq. 34), the number of repeats."""
    last, u, n = [], [], []
    for group in campaign.repeat_groups(idx):
        if group.size < 2:
            raise ValueError(
                f"row {int(group[0]) + 1}: pose {campaign.rows.pose_id[int(group[0])]!r} has 1 reading; "  # type: ignore[index]
                "the uncertainty mode needs at least 2 repeats of every pose"
            )
        rep = repeat_uncertainty(campaign.bar_mm[group][None, :])
        last.append(int(group[-1]))
        u.append(float(rep.u[0]))
        n.append(group.size)
    return np.array(last, dtype=np.intp), np.array(u), np.array(n, dtype=np.int64)


def _nested_summary(nested: NestedResult, b_mm: NDArray[np.float64]) -> dict[str, Any]:
    """The nested correction's rounds, why it stopped, its residual against the expanded uncertainty."""
    return {
        "rounds": [
            {"rms_mm": r.h, "corrected": r.n_corrected, "mean_shift_mm": r.mean_shift} for r in nested.rounds
        ],
        "stop": nested.reason,
        "rms_mm": _rms(nested.residual),
        "flagged": int(nested.flagged.sum()),
        "max_abs_residual_over_b": float(np.max(np.abs(nested.residual) / np.maximum(b_mm, 1e-15))),
    }


def _spread(values: NDArray[np.float64]) -> dict[str, float]:
    return {"mean": float(values.mean()), "min": float(values.min()), "max": float(values.max())}


def fit_ballbar_repeats(
    twists: PoeModel,
    a_deg: NDArray[np.float64],
    reading_mm: NDArray[np.float64],
    u_mm: NDArray[np.float64],
    pivot_mm: NDArray[np.float64],
    fix_near_dependent: bool = False,
    ridge: bool = False,
) -> tuple[BallbarFit, NDArray[np.float64], dict[str, Any]]:
    """The uncertainty mode of spec A.8 on one reading per pose with its standard uncertainty ``u_mm``.

    Returns the weighted fit of the last nested round (its ``cov`` is (JᵀWJ)⁻¹ with W = 1/max(u,
    0.5 µm)², widened by the reduced χ² of the weighted fit when it exceeds 1:
    :func:`~comp_daemon.estimation.uncertainty.covariance_scale`), the nested loop's parameters (the
    model's), and the report: u and b = 1.96·u, the unweighted and weighted fits side by side, every
    nested round.
    ``fix_near_dependent``: the weighted fit's near-dependent pairs are resolved as
    :func:`~comp_daemon.instruments.ballbar.fit_ballbar` does, and the same parameters held in every fit;
    ``ridge`` as there, in every fit.
    """
    b = Z_95 * u_mm
    w = weights_from_uncertainty(u_mm)

    def weighted_fit(values: NDArray[np.float64], **held: Any) -> BallbarFit:
        return fit_ballbar(
            twists, a_deg, values, pivot_mm, weights=w, weights_are_inverse_variance=True, ridge=ridge, **held
        )

    def lengths(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        return ballbar_lengths_mm(twists, a_deg, theta, pivot_mm)

    weighted = weighted_fit(reading_mm, fix_near_dependent=fix_near_dependent)
    held = tuple(p["fixed"] for p in weighted.fixed_pairs)
    unweighted = fit_ballbar(twists, a_deg, reading_mm, pivot_mm, fixed=held, ridge=ridge)
    last = [weighted]

    def identify(values: NDArray[np.float64], warm: NDArray[np.float64] | None) -> NDArray[np.float64]:
        if warm is None:
            return weighted.theta
        last[0] = weighted_fit(values, theta0=warm, fixed=held)
        return last[0].theta

    nested = nested_identification(identify, lengths, reading_mm, b)
    keep = weighted.fitted_index
    chi2_nu, scale = covariance_scale(w, reading_mm - lengths(weighted.theta), keep.size)
    # h_before of the first fit: the nominal model's, not the warm start's
    fit = replace(
        last[0],
        cov=last[0].cov * scale,
        std=last[0].std * np.sqrt(scale),
        h_before_mm=weighted.h_before_mm,
        fixed_pairs=weighted.fixed_pairs,
    )
    report: dict[str, Any] = {
        "method": "spec A.8: last repeat as the reading, u type A (n - 1), b = 1.96 u (95 %), "
        f"weights 1/max(u, {U_FLOOR_MM * 1000:g} um)^2, nested correction (step rule)",
        "poses": int(reading_mm.size),
        "u_mm": _spread(u_mm),
        "b_mm": _spread(b),
        "per_pose": {"u_mm": u_mm.tolist(), "b_mm": b.tolist()},
        "unweighted": {
            "rms_mm": unweighted.h_after_mm,
            "identified": _identified(keep, unweighted.theta, unweighted.std),
        },
        "weighted": {
            "rms_mm": weighted.h_after_mm,
            # reduced chi-square: near 1 when the model explains the readings to their uncertainty
            "chi2_per_dof": chi2_nu,
            "identified": _identified(keep, weighted.theta, weighted.std),
        },
        "nested": _nested_summary(nested, b),
        "rms_mm_to_readings": _rms(reading_mm - lengths(nested.theta)),
        "covariance": "(J^T W J)^-1 x max(1, chi2/dof) = "
        f"x {scale:.3g}: the measurement uncertainty scales the parameters' and the predictions' sigma",
        "covariance_scale": scale,
    }
    return fit, nested.theta, report


def uncertainty_summary(info: dict[str, Any]) -> dict[str, Any] | None:
    """The uncertainty mode's report of a ballbar fit's ``info`` without the per-pose lists (``None``
    for a fit without repeats): what the fit summary prints and the service's job stats carry."""
    unc = info.get("uncertainty")
    if unc is None:
        return None
    nested = unc["nested"]
    return {
        "poses": unc["poses"],
        "repeats": unc["repeats"],
        "u_mm": unc["u_mm"],
        "b_mm": unc["b_mm"],
        "rms_mm": {
            "unweighted": unc["unweighted"]["rms_mm"],
            "weighted": unc["weighted"]["rms_mm"],
            "nested": nested["rms_mm"],
        },
        "chi2_per_dof": unc["weighted"]["chi2_per_dof"],
        "covariance_scale": unc["covariance_scale"],
        "nested_rounds": len(nested["rounds"]),
        "nested_corrected": [r["corrected"] for r in nested["rounds"]],
        "nested_stop": nested["stop"],
        "flagged": nested["flagged"],
    }


@dataclass(frozen=True, slots=True)
class _BallbarSolution:
    """A ballbar campaign's fit on its rows, in either mode (module docstring)."""

    fit: BallbarFit
    theta: NDArray[np.float64]  # the model's 15 parameters (the nested loop's with repeats)
    rows: NDArray[np.intp]  # the campaign rows read: with repeats, each pose's last
    bar_mm: NDArray[np.float64]  # the readings at ``rows``
    rms_mm: float  # RMS length residual of ``theta`` on the readings
    sigma_mm: float | None  # per length, from the repeats; None: from the residual
    uncertainty: dict[str, Any] | None  # the uncertainty mode's report (None without repeats)


def _solve_ballbar(
    campaign: BallbarCampaign,
    idx: NDArray[np.intp],
    twists: PoeModel,
    *,
    fix_near_dependent: bool,
    ridge: bool,
) -> _BallbarSolution:
    """The fit of rows ``idx``: one reading per row, or in the uncertainty mode where the poses repeat."""
    if not campaign.repeated:
        a, bar = campaign.a_deg[idx], campaign.bar_mm[idx]
        fit = fit_ballbar(
            twists, a, bar, campaign.pivot_mm, fix_near_dependent=fix_near_dependent, ridge=ridge
        )
        return _BallbarSolution(fit, fit.theta, idx, bar, fit.h_after_mm, None, None)
    idx, u, counts = _repeat_readings(campaign, idx)
    a, bar = campaign.a_deg[idx], campaign.bar_mm[idx]
    fit, theta, uncertainty = fit_ballbar_repeats(
        twists, a, bar, u, campaign.pivot_mm, fix_near_dependent=fix_near_dependent, ridge=ridge
    )
    uncertainty["repeats"] = {"min": int(counts.min()), "max": int(counts.max())}
    rms = _rms(ballbar_lengths_mm(twists, a, theta, campaign.pivot_mm) - bar)
    sigma = float(np.sqrt(np.mean(np.maximum(u, U_FLOOR_MM) ** 2)))
    return _BallbarSolution(fit, theta, idx, bar, rms, sigma, uncertainty)


def _poe_covariance(solution: _BallbarSolution) -> ParameterCovariance | None:
    """The covariance of the identified POE errors the model carries (None where no POE error was
    fitted or the rows leave no degree of freedom). Its σ per length is the repeats' where the poses
    repeat, else the residual RMS with the degrees of freedom restored, ``h·√(n / (n − p))``."""
    fit, n = solution.fit, int(solution.bar_mm.size)
    keep = fit.fitted_index
    poe_keep = [int(i) for i in keep if i < N_POE_PARAMS]
    if not poe_keep or n <= keep.size:
        return None
    sigma = solution.sigma_mm
    if sigma is None:
        sigma = fit.h_after_mm * float(np.sqrt(n / (n - keep.size)))
    return ParameterCovariance(
        names=tuple(POE_PARAM_NAMES[i] for i in poe_keep),
        values=solution.theta[poe_keep],
        covariance=fit.cov[np.ix_(poe_keep, poe_keep)],
        sigma_mm=sigma,
        rows=n,
    )


def fit_ballbar_campaign(
    robot: RobotDescription,
    campaign: BallbarCampaign,
    rows: NDArray[np.intp] | None = None,
    *,
    fix_near_dependent: bool = False,
    ridge: bool = False,
) -> FittedModel:
    """The ``poe`` model of a ballbar campaign's rows ``rows`` (default: all); a campaign of repeated
    poses in the uncertainty mode (module docstring). ``fix_near_dependent`` holds the weaker of each
    near-dependent pair at zero (:func:`comp_daemon.instruments.ballbar.weaker_of_pairs`); either way the
    pairs are named in ``info["identifiability"]["near_dependent"]`` and those held in
    ``info["near_dependent_fixed"]``. ``ridge`` pulls every POE error toward zero
    (:data:`comp_daemon.instruments.ballbar.RIDGE_SCALES`; ``info["ridge"]`` states it)."""
    idx = np.arange(len(campaign)) if rows is None else np.asarray(rows)
    layout = paper_layout(robot)
    twists = layout_twists(robot, layout)
    solved = _solve_ballbar(campaign, idx, twists, fix_near_dependent=fix_near_dependent, ridge=ridge)
    fit, theta, n_rows, unc = solved.fit, solved.theta, int(solved.bar_mm.size), solved.uncertainty
    model = PoeErrorModel(robot, theta[:N_POE_PARAMS], np.eye(4), layout=layout)
    covariance = _poe_covariance(solved)
    if covariance is not None:
        model.uncertainty = covariance
    keep = fit.fitted_index
    info = _campaign_info(
        "ballbar",
        rows=n_rows,
        rms_mm=solved.rms_mm,
        rank=fit.rank,
        parameters=len(BALLBAR_PARAM_NAMES),
        solver={
            "method": "improved Levenberg-Marquardt, columns scaled"
            + (", weighted 1/u^2, nested correction" if unc else ""),
            "iterations": fit.iterations,
            "stop": fit.reason,
        },
        report=fit.report,
        near_dependent=near_dependent_pairs(
            [BALLBAR_PARAM_NAMES[i] for i in keep], fit.cov[np.ix_(keep, keep)]
        ),
        not_identifiable=[d.describe() for d in fit.null_space],
        identified=_identified(keep, theta, fit.std),
    )
    info.update(
        arcs=sorted({int(k) for k in campaign.arc[solved.rows]}),
        pivot_mm=campaign.pivot_mm.tolist(),
        pivot_offset_mm=theta[N_POE_PARAMS:].tolist(),
        layout=LAYOUTS[layout],
        bar_rms_before_mm=fit.h_before_mm,
        bar_rms_after_mm=solved.rms_mm,
        near_dependent_fixed=list(fit.fixed_pairs),
        ridge=(
            f"each POE error pulled toward zero: {RIDGE_SCALES[0]:g} mm of dl or {RIDGE_SCALES[1]:g} deg of "
            "dtheta cost as much as 1 mm of length residual on one reading"
            if ridge
            else None
        ),
    )
    if unc is not None:
        info["uncertainty"] = unc
    _log.info(
        "ballbar_campaign_fit",
        rows=n_rows,
        rank=fit.rank,
        h_after_mm=solved.rms_mm,
        uncertainty_mode=unc is not None,
    )
    return FittedModel(model, "base", info)


def fit_crossbar_campaign(
    robot: RobotDescription,
    campaign: CrossbarCampaign,
    groups: NDArray[np.intp] | None = None,
    *,
    weighted: bool = True,
) -> FittedModel:
    """The ``kinematic`` model of a cross-bar campaign's groups ``groups`` (default: all): the MDH
    errors and the probe (the robot's TOML tool) from the distance and perpendicularity rows."""
    a, lengths = campaign.readings(groups)
    check_plan(a)
    params = KinematicParams.from_robot(robot)
    before = bar_errors_mm(params, a, robot.sign, lengths)
    fit = calibrate_crossbar(params, a, robot.sign, lengths, weighted=weighted, tool=True)
    kept = np.setdiff1d(np.arange(a.shape[0]), np.asarray(fit.dropped, dtype=np.intp))
    after = bar_errors_mm(fit.params, a[kept], robot.sign, lengths[kept])
    report = fit.report
    rows, rhs = constraint_rows(fit.params, a[kept], robot.sign, lengths[kept], weighted=weighted)
    jac = rows[:, :, report.identifiable_index].reshape(-1, report.identifiable_index.size)
    near: list[dict[str, Any]] = []
    if jac.shape[0] > jac.shape[1]:  # the covariance of the last step's rows, at the solution
        cov, _ = covariance_from_fit(jac, rhs.reshape(-1))
        near = near_dependent_pairs(list(report.identifiable), cov)
    info = _campaign_info(
        "crossbar",
        rows=int(4 * a.shape[0]),
        rms_mm=_rms(after),
        rank=int(report.rank_svd),
        parameters=len(report.candidates),
        solver={
            "method": "Gauss-Newton on distance and perpendicularity rows"
            + (", sqrt(2)L weighting" if weighted else ""),
            "iterations": fit.iterations,
            "stop": fit.reason,
            "step_max": list(fit.step_max),
        },
        report=report,
        near_dependent=near,
        not_identifiable=list(fit.not_identified),
        identified={
            n: {"value": float(fit.dx[i])}
            for n, i in zip(report.identifiable, report.identifiable_index, strict=True)
        },
    )
    info.update(
        crosses=int(a.shape[0]),
        bar_error_max_before_mm=float(np.abs(before).max()),
        bar_error_max_after_mm=float(np.abs(after).max()),
        dropped_crosses=[int(d) for d in fit.dropped],
    )
    _log.info(
        "crossbar_campaign_fit", crosses=int(a.shape[0]), rank=int(report.rank_svd), dropped=fit.dropped
    )
    return FittedModel(KinematicModel(robot, fit.params), "base", info)


#: the model kind each campaign form calibrates
CAMPAIGN_MODELS: dict[str, str] = {"ballbar": "poe", "crossbar": "kinematic"}


def campaign_model(kind: str, model: str | None) -> str:
    """The model a ``kind`` campaign calibrates; ``model`` (a name given by the user) must be it."""
    wanted = CAMPAIGN_MODELS[kind]
    if model is not None and model.strip() not in (wanted, kind):
        raise ValueError(
            f"a {kind} campaign calibrates the {wanted} model (lengths and angles, no positions), "
            f"not {model!r}; name --model {wanted}"
        )
    return wanted


def fit_campaign(
    robot: RobotDescription,
    campaign: Campaign,
    *,
    model: str | None = None,
    seed: int = 0,
    check_fraction: float = 0.0,
    fix_near_dependent: bool = False,
    ridge: bool = False,
) -> tuple[FittedModel, dict[str, Any]]:
    """Fit the model a campaign calibrates on its fit arcs / crosses, and judge it on the check ones.

    The split is the file's (whole arcs or placements), or drawn with ``check_fraction`` and
    ``seed``; the returned dict holds the rows used and the bar errors (mm) of the check arcs or
    crosses before (nominal) and after the calibration (empty without check rows).
    ``fix_near_dependent`` and ``ridge`` (ballbar campaigns): :func:`fit_ballbar_campaign`'s.
    """
    if isinstance(campaign, BallbarCampaign):
        campaign_model("ballbar", model)
        fit_rows, check_rows, drawn = campaign.split(seed=seed, check_fraction=check_fraction)
        fitted = fit_ballbar_campaign(
            robot, campaign, fit_rows, fix_near_dependent=fix_near_dependent, ridge=ridge
        )
        check: dict[str, Any] = {
            "fit_rows": int(fit_rows.size),
            "check_rows": int(check_rows.size),
            "drawn": drawn,
        }
        if check_rows.size:
            assert isinstance(fitted.model, PoeErrorModel)
            twists = fitted.model.twists
            a, bar = campaign.a_deg[check_rows], campaign.bar_mm[check_rows]
            before = (
                ballbar_lengths_mm(twists, a, np.zeros(len(BALLBAR_PARAM_NAMES)), campaign.pivot_mm) - bar
            )
            theta = np.concatenate([fitted.model.x, fitted.info["pivot_offset_mm"]])
            after = ballbar_lengths_mm(twists, a, theta, campaign.pivot_mm) - bar
            check["bar_error_rms_mm"] = {"before": _rms(before), "after": _rms(after)}
        return fitted, check
    campaign_model("crossbar", model)
    fit_groups, check_groups, drawn = campaign.split(seed=seed, check_fraction=check_fraction)
    fitted = fit_crossbar_campaign(robot, campaign, fit_groups)
    check = {"fit_rows": int(4 * fit_groups.size), "check_rows": int(4 * check_groups.size), "drawn": drawn}
    if check_groups.size:
        a, lengths = campaign.readings(check_groups)
        nominal = KinematicParams.from_robot(robot)
        params = fitted.model.ik_params()
        check["bar_error_rms_mm"] = {
            "before": _rms(bar_errors_mm(nominal, a, robot.sign, lengths)),
            "after": _rms(bar_errors_mm(params, a, robot.sign, lengths)),
        }
    return fitted, check


def _rms(values: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def registered_prediction(
    model: ErrorModel,
    a_fit_deg: NDArray[np.float64],
    xyz_fit_mm: NDArray[np.float64],
    a_check_deg: NDArray[np.float64],
    payload_fit: NDArray[np.float64] | float = 0.0,
    payload_check: NDArray[np.float64] | float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The model's predictions of the check rows in the measurement frame, and that frame
    (``meas_T_model``, 4×4): the rigid motion that best maps its predictions of the fit rows onto
    the measured ones. Only the frame is fitted; the model's parameters stay as calibrated."""
    p_fit = model.predict_tcp_mm(a_fit_deg, payload_kg=payload_fit)
    frame = rigid_registration(p_fit, np.asarray(xyz_fit_mm, dtype=float))
    return transform_points(frame, model.predict_tcp_mm(a_check_deg, payload_kg=payload_check)), frame
