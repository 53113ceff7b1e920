"""Fit any model kind on measured rows: the entry point of the ``fit`` and ``evaluate`` commands.

``fit_model(kind, robot, a_deg, xyz_mm, …)`` returns the model, the frame the data were in and a
JSON-ready summary of the fit (rows, RMS, solver, identifiability, order selection). Kinds:

- ``nominal``: the robot description; only the frame is registered (tracker data), nothing fitted;
- ``kinematic``: MDH calibration (:func:`comp_daemon.models.kinematic.calibrate_kinematic`), with
  the optional joint ``effects`` (seed 001: ``ratio``, ``backlash``);
- ``chebyshev``: the Chebyshev error model (:func:`comp_daemon.models.chebyshev.fit_chebyshev`);
  without an ``order`` the order and the removal threshold are chosen by k-fold cross-validation on
  the rows given.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.base import ErrorModel, NominalModel, as_axes
from comp_daemon.models.chebyshev import CHEBYSHEV_RTOL, fit_chebyshev, n_coefficients, select_order
from comp_daemon.models.identifiability import IdentifiabilityReport
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.lm import LMResult
from comp_daemon.models.registration import detect_frame, rigid_registration
from comp_daemon.robot.description import RobotDescription

__all__ = ["FITTABLE_KINDS", "FittedModel", "fit_model", "max_parameters"]

FITTABLE_KINDS = ("nominal", "kinematic", "chebyshev")
FrameChoice = Literal["auto", "base", "tracker"]


@dataclass(frozen=True, slots=True)
class FittedModel:
    model: ErrorModel
    frame: Literal["base", "tracker"]
    info: dict[str, Any]


def max_parameters(kind: str, order: int | None = None, n_effect_params: int = 0) -> int:
    """Parameters of the chosen model before the identifiability analysis (a row-count floor)."""
    if kind == "nominal":
        return 6
    if kind == "kinematic":
        return 39 + n_effect_params
    if kind == "chebyshev":
        return n_coefficients(0 if order is None else order)
    raise ValueError(f"unknown model kind '{kind}' (known: {', '.join(FITTABLE_KINDS)})")


def _lm_info(lm: LMResult) -> dict[str, Any]:
    return {
        "method": "improved Levenberg-Marquardt (seed 000)",
        "iterations": lm.iterations,
        "converged": lm.converged,
        "stop": lm.reason,
        "residual_evaluations": lm.n_residual_evals,
        "jacobian_evaluations": lm.n_jacobian_evals,
        "time_s": lm.time_s,
        "final_cost_mm2": lm.cost,
    }


def _report_info(report: IdentifiabilityReport, list_removed: bool = True) -> dict[str, Any]:
    out: dict[str, Any] = {
        "candidates": len(report.candidates),
        "identifiable": len(report.identifiable),
        "rank_qr": report.rank_qr,
        "rank_svd": report.rank_svd,
        "condition_number": report.condition_number,
    }
    if list_removed:
        out["removed"] = [
            {
                "name": r.name,
                "reason": r.reason,
                "depends_on": list(r.depends_on),
                "coefficients": list(r.coefficients),
            }
            for r in report.removed
        ]
    else:
        out["removed"] = [r.name for r in report.removed]
    return out


def fit_model(
    kind: str,
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    xyz_mm: NDArray[np.float64],
    *,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
    order: int | None = None,
    effects: Sequence[str] = (),
    frame: FrameChoice = "auto",
    cv_folds: int = 5,
    seed: int = 0,
) -> FittedModel:
    """Fit a model of ``kind`` on these rows (module docstring)."""
    a = as_axes(a_deg)
    p = np.asarray(xyz_mm, dtype=float)
    n = a.shape[0]
    if kind not in FITTABLE_KINDS:
        raise ValueError(f"unknown model kind '{kind}' (known: {', '.join(FITTABLE_KINDS)})")
    if kind == "nominal":
        nominal = KinematicParams.from_robot(robot)
        p_nom = tcp_position_mm(nominal, axes_deg_to_q_rad(a, nominal.sign))
        chosen = detect_frame(p_nom, p) if frame == "auto" else frame
        reg = rigid_registration(p_nom, p) if chosen == "tracker" else np.eye(4)
        model = NominalModel(robot, reg)
        err = model.predict_tcp_mm(a) - p
        info = {"kind": kind, "rows": n, "rms_mm": float(np.sqrt(np.mean(np.sum(err**2, axis=1))))}
        return FittedModel(model, chosen, info)
    if kind == "kinematic":
        kf = calibrate_kinematic(
            robot, a, p, dir=dir, payload_kg=payload_kg, temp_c=temp_c, effects=effects, frame=frame
        )
        info = {
            "kind": kind,
            "rows": n,
            "rms_mm": kf.rms_mm,
            "effects": list(effects),
            "solver": _lm_info(kf.lm),
            "identifiability": _report_info(kf.report),
            "identified": {
                name: {"value": float(v), "std": float(s)}
                for name, v, s in zip(kf.identified, kf.values, kf.std, strict=True)
            },
        }
        return FittedModel(kf.model, kf.frame, info)
    if effects:
        raise ValueError("joint effects belong to the kinematic model; the Chebyshev model has none")
    selection_info: dict[str, Any] | None = None
    rtol = CHEBYSHEV_RTOL
    if order is None:
        sel = select_order(robot, a, p, folds=min(cv_folds, n), seed=seed, frame=frame)
        order, rtol = sel.order, sel.rtol
        selection_info = {
            "method": f"{sel.folds}-fold cross-validation on the fit rows (mean held-out 3-D RMS, mm)",
            "orders": list(sel.orders),
            "rtols": list(sel.rtols),
            "cv_rms_mm": [list(r) for r in sel.cv_rms_mm],
            "chosen_order": sel.order,
            "chosen_rtol": sel.rtol,
        }
    cf = fit_chebyshev(robot, a, p, order, frame=frame, rtol=rtol)
    info = {
        "kind": kind,
        "rows": n,
        "order": order,
        "rtol": rtol,
        "range_deg": cf.model.range_deg.tolist(),
        "rms_mm": cf.rms_mm,
        "solver": _lm_info(cf.lm),
        "identifiability": _report_info(cf.report, list_removed=False),
        "order_selection": selection_info,
    }
    return FittedModel(cf.model, cf.frame, info)
