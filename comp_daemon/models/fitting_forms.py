"""Fitting the kinds whose paper's form sits beside the product's: ``compliance`` and ``poe``.

Same signature as :mod:`comp_daemon.models.fitting` (``fit_<kind>(robot, rows, spec, options)``):

- ``compliance``: the kinematic calibration (every MDH parameter, base frame and tool) with seed
  004's joint compliance C2, C3 under the gravity torques of the links and the payload of each row
  (``payload_kg``), the compliance kept only if it earns its place out of fold
  (:func:`comp_daemon.models.fitting.select_effects`; always with ``:all``); ``compliance:paper``
  the paper's own form, zero offsets and C2, C3 on the nominal geometry;
- ``poe``: a product-of-exponentials calibration with a full twist error per joint and the tool
  offset (:mod:`comp_daemon.models.poe.twist`); ``poe:paper`` seed 002's errors ``dl1..dl6``,
  ``dtheta1..dtheta6``; both with the base frame (:func:`comp_daemon.models.poe.model.fit_poe`), the
  dependent parameters removed by name and the directions the data do not see listed.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from comp_daemon.estimation.registration import detect_frame, rigid_registration
from comp_daemon.estimation.selection import keep_all
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.compliance import COMPLIANCE_JOINTS, ComplianceFit, calibrate_compliance
from comp_daemon.models.covariance import attach_covariance
from comp_daemon.models.fitting import (
    FitOptions,
    FittedModel,
    ModelSpec,
    identified_info,
    lm_info,
    report_info,
    select_effects,
)
from comp_daemon.models.poe.calibration import LAYOUTS
from comp_daemon.models.poe.model import fit_poe
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["fit_compliance_kind", "fit_poe_kind"]


def fit_compliance_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """Seed 004's compliance of joints 2 and 3 under the rows' payloads, on the whole kinematic
    geometry (``compliance``; the compliance kept only if it earns its place, every time with
    ``:all``) or on the zero offsets alone (``compliance:paper``, the paper's form)."""
    geometry = not spec.paper

    def calibrate(effs: Sequence[str], sub: MeasuredRows, fo: FitOptions) -> ComplianceFit:
        return calibrate_compliance(
            robot,
            sub.a_deg,
            sub.xyz_mm,
            payload_kg=sub.payload_kg,
            compliance_joints=COMPLIANCE_JOINTS if "compliance" in effs else (),
            frame=fo.frame,
            geometry=geometry,
        )

    kept: tuple[str, ...] = ("compliance",)
    if spec.paper:
        selection = keep_all(kept)
    else:
        kept, selection = select_effects(
            robot, rows, spec, options, ("compliance",), lambda e, sub, fo: calibrate(e, sub, fo).model
        )
    cf = calibrate(kept, rows, options)
    attach_covariance(cf.model, cf.identified, cf.values, cf.lm.jacobian, cf.lm.residual)
    info = {
        "kind": spec.kind,
        "rows": rows.n,
        "form": "zero offsets and C2, C3 (seed 004)" if spec.paper else "kinematic geometry and C2, C3",
        "rms_mm": cf.rms_mm,
        "compliance_rad_per_nm": cf.model.compliance_rad_per_nm.tolist(),
        "zero_offset_rad": cf.model.zero_offset_rad.tolist(),
        "solver": lm_info(cf.lm),
        "identifiability": report_info(cf.report),
        "identified": identified_info(cf.identified, cf.values, cf.std),
        "selection": selection.to_info(),
    }
    return FittedModel(cf.model, cf.frame, info)


def fit_poe_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """The POE calibration: a twist error per joint, the tool offset and the base frame
    (``poe``), or seed 002's errors Δl, Δθ and the base frame (``poe:paper``)."""
    nominal = KinematicParams.from_robot(robot)
    p_nom = tcp_position_mm(nominal, axes_deg_to_q_rad(rows.a_deg, nominal.sign))
    chosen = detect_frame(p_nom, rows.xyz_mm) if options.frame == "auto" else options.frame
    reg = rigid_registration(p_nom, rows.xyz_mm) if chosen == "tracker" else np.eye(4)
    pf = fit_poe(robot, rows.a_deg, rows.xyz_mm, reg, "paper" if spec.paper else "twist")
    fit = pf.fit
    keep = fit.report.identifiable_index
    info = {
        "kind": spec.kind,
        "rows": rows.n,
        "form": "dl1..dl6, dtheta1..dtheta6 (seed 002)"
        if spec.paper
        else "a twist error per joint (dtheta, dwu, dwn, dpu, dpn, dlax) and the tool offset",
        "rms_mm": pf.rms_mm,
        **({"layout": LAYOUTS[pf.model.layout]} if spec.paper else {}),
        "solver": {
            "method": "improved Levenberg-Marquardt (seed 000), columns scaled",
            "iterations": fit.iterations,
            "stop": fit.reason,
        },
        "identifiability": report_info(fit.report),
        "not_identifiable": [d.describe() for d in fit.null_space],
        # the base parameters are increments of the rigid start frame; removed parameters stay 0
        "identified": identified_info([fit.names[i] for i in keep], fit.theta[keep], fit.std[keep]),
    }
    return FittedModel(pf.model, chosen, info)
