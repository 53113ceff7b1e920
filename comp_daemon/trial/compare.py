"""Seed 001's model comparison on the trial's own data.

Seed 001 compares, on validation points, the positioning error left by a kinematic calibration
(MDH + base + TCP), by the same calibration extended with reduction-ratio errors and joint backlash
(§1), and by the error-similarity model — ordinary kriging of the remaining error in joint space,
with the backlash identified (§2) — against kriging without it ("method one"). Here every model is
fitted on the trial's sampling points and judged on its target points measured with the commands
of the nominal program (the "uncompensated" run, or the "feedback only" run for the closed-loop
data): the error of a model is ``measured − predicted`` at those commands (seed 001's validation).
Seed 000's Chebyshev model (the trial's order, and the order chosen by cross-validation) is judged
the same way, so every method of both papers is compared on one data set.

Models come from :mod:`comp_daemon.models` (``registry.fit_model``, ``kriging.fit_kriging``); numbers
are mm, Table 2 statistics (:func:`comp_daemon.models.evaluation.error_statistics`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.models.base import ErrorModel
from comp_daemon.models.evaluation import error_statistics
from comp_daemon.models.kriging import fit_kriging
from comp_daemon.models.registry import fit_model
from comp_daemon.robot.description import RobotDescription

__all__ = ["ComparisonData", "compare_models"]

Maker = Callable[[], tuple[ErrorModel, dict[str, Any]]]


@dataclass(frozen=True, slots=True)
class ComparisonData:
    """Fit rows (sampling points) and check rows (target points), all as commanded and measured."""

    a_fit_deg: NDArray[np.float64]
    p_fit_mm: NDArray[np.float64]
    dir_fit: NDArray[np.float64]
    a_check_deg: NDArray[np.float64]
    p_check_mm: NDArray[np.float64]
    dir_check: NDArray[np.float64]
    payload_kg: float = 0.0


def compare_models(
    robot: RobotDescription, data: ComparisonData, *, chebyshev_order: int, cross_validate: bool = True
) -> dict[str, Any]:
    """Fit each model on the fit rows, judge it on the check rows; ``{"models": {label: {...}}}``.

    Each entry: ``paper`` (whose method), ``table2`` (or ``error`` when the model could not be
    fitted on these rows), ``fit_time_s``, and the model's own details (order, direction separation).
    """
    d = data
    fit_kw: dict[str, Any] = {"dir": d.dir_fit, "payload_kg": d.payload_kg, "frame": "base"}
    out: dict[str, Any] = {
        "rows": {"fit": len(d.a_fit_deg), "check": len(d.a_check_deg)},
        "error": "measured − predicted at the commanded axis values of the check rows (mm)",
        "models": {},
    }
    fitted: dict[str, ErrorModel] = {}

    def judge(label: str, paper: str, make: Maker) -> None:
        t0 = time.perf_counter()
        entry: dict[str, Any] = {"paper": paper}
        try:
            model, details = make()
        except (ValueError, np.linalg.LinAlgError) as exc:
            entry["error"] = str(exc)
        else:
            fitted[label] = model
            pred = model.predict_tcp_mm(d.a_check_deg, d.dir_check, d.payload_kg)
            entry["table2"] = error_statistics(d.p_check_mm, pred)
            entry.update(details)
        entry["fit_time_s"] = round(time.perf_counter() - t0, 3)
        out["models"][label] = entry

    def fitted_model(kind: str, **kw: Any) -> Maker:
        def make() -> tuple[ErrorModel, dict[str, Any]]:
            fm = fit_model(kind, robot, d.a_fit_deg, d.p_fit_mm, **fit_kw, **kw)
            details: dict[str, Any] = {"fit_rms_mm": fm.info.get("rms_mm")}
            if kind == "chebyshev":
                details["order"] = fm.model.order
            return fm.model, details

        return make

    def kriged(
        base_label: str, direction: Literal["aware", "blind"]
    ) -> Callable[[], tuple[ErrorModel, dict[str, Any]]]:
        def make() -> tuple[ErrorModel, dict[str, Any]]:
            base = fitted.get(base_label)
            if base is None:
                raise ValueError(f"its base model ({base_label}) could not be fitted")
            kf = fit_kriging(
                base, d.a_fit_deg, d.p_fit_mm, dir=d.dir_fit, payload_kg=d.payload_kg, direction=direction
            )
            return kf.model, {
                "dir_separation_deg": float(kf.model.metric.dir_separation_deg[0]),
                "variograms": [v.kind for v in kf.model.variograms],
                "loo_rms_mm": kf.loo_rms_mm,
            }

        return make

    judge("nominal", "—", fitted_model("nominal"))
    judge("kinematic", "seed 000 baseline, seed 001 §1 (MDH + base + TCP)", fitted_model("kinematic"))
    judge(
        "kinematic + ratio + backlash",
        "seed 001 §1",
        fitted_model("kinematic:all", effects=("ratio", "backlash")),
    )
    judge(
        "kriging (direction-aware) on kinematic + ratio + backlash",
        "seed 001 §2",
        kriged("kinematic + ratio + backlash", "aware"),
    )
    judge("kriging (blind) on kinematic", "seed 001's 'method one'", kriged("kinematic", "blind"))
    judge(f"Chebyshev m={chebyshev_order}", "seed 000 §2.1", fitted_model("chebyshev", order=chebyshev_order))
    if cross_validate:
        judge(
            "Chebyshev, order by cross-validation",
            "seed 000 §2.1 (order chosen)",
            fitted_model("chebyshev", order="cv"),
        )
    return out
