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

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.data.ballbar import BallbarCampaign
from comp_daemon.data.campaigns import Campaign
from comp_daemon.data.crossbar import CrossbarCampaign
from comp_daemon.estimation.registration import rigid_registration, transform_points
from comp_daemon.estimation.uncertainty import (
    U_FLOOR_MM,
    Z_95,
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


def _identified(names: list[str], values: NDArray[np.float64], std: NDArray[np.float64]) -> dict[str, Any]:
    return {n: {"value": float(v), "std": float(s)} for n, v, s in zip(names, values, std, strict=True)}


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
    0.5 µm)², widened by the reduced χ² of the weighted fit when it exceeds 1: a model that does not
    explain the readings to their uncertainty), the nested loop's parameters (the model's), and the
    report: u and b = 1.96·u, the unweighted and weighted fits side by side, every nested round.
    ``fix_near_dependent``: the weighted fit's near-dependent pairs are resolved as
    :func:`~comp_daemon.instruments.ballbar.fit_ballbar` does, and the same parameters held in every fit;
    ``ridge`` as there, in every fit.
    """
    b = Z_95 * u_mm
    w = weights_from_uncertainty(u_mm)
    weighted = fit_ballbar(
        twists,
        a_deg,
        reading_mm,
        pivot_mm,
        weights=w,
        weights_are_inverse_variance=True,
        fix_near_dependent=fix_near_dependent,
        ridge=ridge,
    )
    held = tuple(p["fixed"] for p in weighted.fixed_pairs)
    unweighted = fit_ballbar(twists, a_deg, reading_mm, pivot_mm, fixed=held, ridge=ridge)
    last = [weighted]

    def identify(values: NDArray[np.float64], warm: NDArray[np.float64] | None) -> NDArray[np.float64]:
        if warm is None:
            return weighted.theta
        last[0] = fit_ballbar(
            twists,
            a_deg,
            values,
            pivot_mm,
            weights=w,
            weights_are_inverse_variance=True,
            theta0=warm,
            fixed=held,
            ridge=ridge,
        )
        return last[0].theta

    nested = nested_identification(
        identify, lambda th: ballbar_lengths_mm(twists, a_deg, th, pivot_mm), reading_mm, b
    )
    keep = weighted.fitted_index
    residual = reading_mm - ballbar_lengths_mm(twists, a_deg, nested.theta, pivot_mm)
    chi2 = float(np.sum(w * (reading_mm - ballbar_lengths_mm(twists, a_deg, weighted.theta, pivot_mm)) ** 2))
    chi2_nu = chi2 / max(reading_mm.size - keep.size, 1)
    # a model that does not explain the readings to their uncertainty (χ²/ν > 1) widens the covariance
    scale = max(1.0, chi2_nu)
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
        "u_mm": {"mean": float(u_mm.mean()), "min": float(u_mm.min()), "max": float(u_mm.max())},
        "b_mm": {"mean": float(b.mean()), "min": float(b.min()), "max": float(b.max())},
        "per_pose": {"u_mm": u_mm.tolist(), "b_mm": b.tolist()},
        "unweighted": {
            "rms_mm": unweighted.h_after_mm,
            "identified": _identified(
                [BALLBAR_PARAM_NAMES[i] for i in keep], unweighted.theta[keep], unweighted.std[keep]
            ),
        },
        "weighted": {
            "rms_mm": weighted.h_after_mm,
            # reduced chi-square: near 1 when the model explains the readings to their uncertainty
            "chi2_per_dof": chi2_nu,
            "identified": _identified(
                [BALLBAR_PARAM_NAMES[i] for i in keep], weighted.theta[keep], weighted.std[keep]
            ),
        },
        "nested": {
            "rounds": [
                {"rms_mm": r.h, "corrected": r.n_corrected, "mean_shift_mm": r.mean_shift}
                for r in nested.rounds
            ],
            "stop": nested.reason,
            "rms_mm": float(np.sqrt(np.mean(nested.residual**2))),
            "flagged": int(nested.flagged.sum()),
            "max_abs_residual_over_b": float(np.max(np.abs(nested.residual) / np.maximum(b, 1e-15))),
        },
        "rms_mm_to_readings": float(np.sqrt(np.mean(residual**2))),
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
    uncertainty: dict[str, Any] | None = None
    if campaign.repeated:
        idx, u, counts = _repeat_readings(campaign, idx)
        a, bar = campaign.a_deg[idx], campaign.bar_mm[idx]
        fit, theta, uncertainty = fit_ballbar_repeats(
            twists, a, bar, u, campaign.pivot_mm, fix_near_dependent=fix_near_dependent, ridge=ridge
        )
        uncertainty["repeats"] = {"min": int(counts.min()), "max": int(counts.max())}
        h_after = _rms(ballbar_lengths_mm(twists, a, theta, campaign.pivot_mm) - bar)
        sigma = float(np.sqrt(np.mean(np.maximum(u, U_FLOOR_MM) ** 2)))  # per length, from the repeats
    else:
        a, bar = campaign.a_deg[idx], campaign.bar_mm[idx]
        fit = fit_ballbar(
            twists, a, bar, campaign.pivot_mm, fix_near_dependent=fix_near_dependent, ridge=ridge
        )
        theta, h_after = fit.theta, fit.h_after_mm
    model = PoeErrorModel(robot, theta[:N_POE_PARAMS], np.eye(4), layout=layout)
    keep = fit.fitted_index
    poe_keep = [int(i) for i in keep if i < N_POE_PARAMS]
    if poe_keep and bar.size > keep.size:
        if uncertainty is None:
            sigma = fit.h_after_mm * float(np.sqrt(bar.size / (bar.size - keep.size)))  # per length
        model.uncertainty = ParameterCovariance(
            names=tuple(POE_PARAM_NAMES[i] for i in poe_keep),
            values=theta[poe_keep],
            covariance=fit.cov[np.ix_(poe_keep, poe_keep)],
            sigma_mm=sigma,
            rows=int(bar.size),
        )
    info: dict[str, Any] = {
        "kind": "ballbar",
        "campaign": "ballbar",
        "rows": int(bar.size),
        "arcs": sorted({int(k) for k in campaign.arc[idx]}),
        "pivot_mm": campaign.pivot_mm.tolist(),
        "pivot_offset_mm": theta[N_POE_PARAMS:].tolist(),
        "layout": LAYOUTS[layout],
        "rms_mm": h_after,
        "bar_rms_before_mm": fit.h_before_mm,
        "bar_rms_after_mm": h_after,
        "rank": fit.rank,
        "parameters": len(BALLBAR_PARAM_NAMES),
        "solver": {
            "method": "improved Levenberg-Marquardt, columns scaled"
            + (", weighted 1/u^2, nested correction" if uncertainty else ""),
            "iterations": fit.iterations,
            "stop": fit.reason,
        },
        "identifiability": {
            **report_info(fit.report),
            "near_dependent": near_dependent_pairs(
                [BALLBAR_PARAM_NAMES[i] for i in keep], fit.cov[np.ix_(keep, keep)]
            ),
        },
        "not_identifiable": [d.describe() for d in fit.null_space],
        "near_dependent_fixed": list(fit.fixed_pairs),
        "ridge": (
            f"each POE error pulled toward zero: {RIDGE_SCALES[0]:g} mm of dl or {RIDGE_SCALES[1]:g} deg of "
            "dtheta cost as much as 1 mm of length residual on one reading"
            if ridge
            else None
        ),
        "identified": _identified([BALLBAR_PARAM_NAMES[i] for i in keep], theta[keep], fit.std[keep]),
        "frame": "robot base (nominal); a tracker frame is registered on tracker data",
    }
    if uncertainty is not None:
        info["uncertainty"] = uncertainty
    _log.info(
        "ballbar_campaign_fit",
        rows=int(bar.size),
        rank=fit.rank,
        h_after_mm=h_after,
        uncertainty_mode=uncertainty is not None,
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
    info: dict[str, Any] = {
        "kind": "crossbar",
        "campaign": "crossbar",
        "rows": int(4 * a.shape[0]),
        "crosses": int(a.shape[0]),
        "rms_mm": float(np.sqrt(np.mean(after**2))),
        "bar_error_max_before_mm": float(np.abs(before).max()),
        "bar_error_max_after_mm": float(np.abs(after).max()),
        "rank": int(report.rank_svd),
        "parameters": len(report.candidates),
        "solver": {
            "method": "Gauss-Newton on distance and perpendicularity rows"
            + (", sqrt(2)L weighting" if weighted else ""),
            "iterations": fit.iterations,
            "stop": fit.reason,
            "step_max": list(fit.step_max),
        },
        "dropped_crosses": [int(d) for d in fit.dropped],
        "identifiability": {**report_info(report), "near_dependent": near},
        "not_identifiable": list(fit.not_identified),
        "identified": {
            n: {"value": float(fit.dx[i])}
            for n, i in zip(report.identifiable, report.identifiable_index, strict=True)
        },
        "frame": "robot base (nominal); a tracker frame is registered on tracker data",
    }
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
