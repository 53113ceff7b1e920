"""The POE calibration (seed 002) as an error model: ``poe`` in the model registry.

:class:`PoeErrorModel` predicts the TCP with the product-of-exponentials chain of
:mod:`comp_daemon.kinematics.poe` built from the robot description (equal to the MDH model at
nominal), in its fitted base frame ``world_T_base``, carrying either the paper's 12 errors
``dl1..dl6`` (mm) and ``dtheta1..dtheta6`` (rad) (``poe:paper``) or a full twist error per joint and
a tool offset error (``poe``, :mod:`comp_daemon.models.poe.twist`: 39 errors, the dependent ones
removed by name). The paper's 12 sit on seed 002's own segment layout (Table 1) where the robot is
its IRB 120, else on one segment per joint point (``layout``, stored in the artifact when it is
Table 1's; :func:`comp_daemon.models.poe.calibration.paper_layout`)::

    TCP_world = world_T_base · p_POE(A; x)

:func:`fit_poe` identifies them from measured positions with
:func:`comp_daemon.models.poe.calibration.fit_poe_positions` (the base frame always fitted: on tracker data it
starts from the rigid registration, on base-frame data it takes up the POE errors' dependent
directions ``dtheta1``, ``dl2``; the dependent parameters are removed by name and stay zero).

Compensation. The POE chain has no MDH parameters of its own: :meth:`ik_params` is the robot's
nominal MDH chain in the model's fitted base frame (the base class's), which seeds the inverse
kinematics; the compensation's fixed-point iteration then moves the IK target by the model's own
prediction error (:func:`comp_daemon.models.compensation.compensate`), so the result is the POE
model's, not the nominal chain's.

Uncertainty. The fit's parameter covariance (:class:`comp_daemon.models.covariance.ParameterCovariance`)
is taken at the solution over the identified parameters, the base parameters as local increments
about the fitted frame (value 0; translation mm, rotation vector rad on the left), so the stored
``values`` are the POE errors and zeros; :meth:`parameter_jacobian` propagates it through the same
Jacobian (:func:`comp_daemon.models.poe.calibration.poe_world_jacobian`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.poe import N_POE_PARAMS, POE_PARAM_NAMES, PoeModel
from comp_daemon.models.base import ErrorModel, Query, StoredModel, as_axes, finite_array
from comp_daemon.models.covariance import ParameterCovariance
from comp_daemon.models.fitting import (
    FitOptions,
    FittedModel,
    ModelSpec,
    identified_info,
    report_info,
)
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.kinematic import registered_start
from comp_daemon.models.poe.calibration import (
    BASE_NAMES,
    LAYOUTS,
    PoeFit,
    PoeLayout,
    fit_poe_positions,
    layout_twists,
    paper_layout,
    poe_world_jacobian,
    poe_world_position_mm,
)
from comp_daemon.models.poe.twist import (
    N_TWIST_PARAMS,
    TWIST_PARAM_NAMES,
    PoeTwistFit,
    fit_poe_twists,
    twist_chain,
    twist_world_jacobian,
)
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["KIND", "POE_MODEL_NAMES", "PoeErrorFit", "PoeErrorModel", "fit_poe", "fit_poe_kind"]

POE_MODEL_NAMES: tuple[str, ...] = POE_PARAM_NAMES + BASE_NAMES


class PoeErrorModel(ErrorModel):
    """POE chain with the seed-002 errors ``x`` (12,) in the frame ``world_T_base`` (module docstring)."""

    kind: ClassVar[str] = "poe"

    def __init__(
        self,
        robot: RobotDescription,
        x: NDArray[np.float64],
        world_T_base: NDArray[np.float64],
        registration: NDArray[np.float64] | None = None,
        twist: NDArray[np.float64] | None = None,
        layout: PoeLayout = "robot",
    ) -> None:
        self.robot = robot
        self.x = finite_array(x, (N_POE_PARAMS,), "POE errors x")
        self.twist = None if twist is None else finite_array(twist, (N_TWIST_PARAMS,), "POE twist errors")
        if self.twist is not None and np.any(self.x != 0.0):
            raise ValueError("a POE model carries the 12 paper errors or the twist errors, not both")
        self.world_T_base = finite_array(world_T_base, (4, 4), "world_T_base")
        self.registration = np.eye(4) if registration is None else np.array(registration, dtype=float)
        if self.twist is not None and layout != "robot":
            raise ValueError("the twist errors are fitted on the robot file's layout")
        self.layout: PoeLayout = layout
        self.twists: PoeModel = layout_twists(robot, layout)

    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        if self.twist is not None:
            p, _ = twist_chain(self.twists, query.a, self.twist)
            return p @ self.world_T_base[:3, :3].T + self.world_T_base[:3, 3]
        return poe_world_position_mm(self.twists, query.a, self.x, self.world_T_base)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The names :meth:`parameter_jacobian` takes: the model's errors, then the base frame."""
        return (TWIST_PARAM_NAMES if self.twist is not None else POE_PARAM_NAMES) + BASE_NAMES

    def parameter_jacobian(
        self, names: Sequence[str], values: NDArray[np.float64], query: Query
    ) -> NDArray[np.float64]:
        """(n, 3, p) derivative of the TCP w.r.t. ``names`` (of :data:`POE_MODEL_NAMES`; base
        parameters as increments about the fitted frame), at the model's own errors (``values``
        are those errors and the base increments' zeros)."""
        if self.twist is not None:
            theta = np.concatenate([self.twist, np.zeros(len(BASE_NAMES))])
            _, jac = twist_world_jacobian(self.twists, query.a, theta, self.world_T_base)
        else:
            theta = np.concatenate([self.x, np.zeros(len(BASE_NAMES))])
            _, jac = poe_world_jacobian(self.twists, query.a, theta, self.world_T_base)
        known = self.parameter_names
        try:
            cols = [known.index(n) for n in names]
        except ValueError:
            raise ValueError(f"uncertainty: POE parameters are {', '.join(known)}") from None
        return jac[:, :, cols]

    def to_payload(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "names": list(POE_PARAM_NAMES),
            "x": self.x.tolist(),
            "world_T_base": self.world_T_base.tolist(),
        }
        if self.layout != "robot":  # an artifact without it has the robot file's layout
            out["layout"] = self.layout
        if self.twist is not None:
            out["twist_names"] = list(TWIST_PARAM_NAMES)
            out["twist"] = self.twist.tolist()
        return out

    @classmethod
    def from_stored(cls, stored: StoredModel) -> PoeErrorModel:
        robot, payload = stored.robot, stored.payload
        names = [str(n) for n in payload["names"]]
        if names != list(POE_PARAM_NAMES):
            raise ValueError(f"model field 'names': expected {list(POE_PARAM_NAMES)}, got {names}")
        x = finite_array(payload["x"], (N_POE_PARAMS,), "model field 'x'")
        frame = finite_array(payload["world_T_base"], (4, 4), "model field 'world_T_base'")
        twist = None
        if payload.get("twist") is not None:
            twist_names = [str(n) for n in payload.get("twist_names", ())]
            if twist_names != list(TWIST_PARAM_NAMES):
                raise ValueError(f"model field 'twist_names': expected {list(TWIST_PARAM_NAMES)}")
            twist = finite_array(payload["twist"], (N_TWIST_PARAMS,), "model field 'twist'")
        layout = payload.get("layout", "robot")
        if layout not in LAYOUTS:
            raise ValueError(f"model field 'layout': expected one of {', '.join(LAYOUTS)}, got {layout!r}")
        if layout != paper_layout(robot) and layout != "robot":
            raise ValueError(f"model field 'layout': {layout!r} is not a layout of the robot {robot.name}")
        return cls(robot, x, frame, stored.registration, twist, layout)


@dataclass(frozen=True, slots=True)
class PoeErrorFit:
    """The fitted model, the calibration behind it and the residual RMS (mm) of the model."""

    model: PoeErrorModel
    fit: PoeFit | PoeTwistFit
    rms_mm: float


def fit_poe(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    p_mm: NDArray[np.float64],
    registration: NDArray[np.float64],
    form: Literal["twist", "paper"] = "twist",
) -> PoeErrorFit:
    """The POE errors and the base frame from measured TCPs ``p_mm`` (n, 3) at ``a_deg`` (n, 6):
    the twist errors and the tool offset error (``form="twist"``) or the paper's 12 (``"paper"``, on
    seed 002's Table 1 layout where the robot is the paper's IRB 120,
    :func:`~comp_daemon.models.poe.calibration.paper_layout`);
    ``registration`` is the frame the model reports as its measurement frame (identity on base-frame
    data). The model carries the fit's parameter covariance when there are residual degrees of freedom."""
    a = as_axes(a_deg)
    p = np.asarray(p_mm, dtype=float)
    fit: PoeFit | PoeTwistFit
    if form == "twist":
        fit = fit_poe_twists(PoeModel.from_robot(robot), a, p)
        model = PoeErrorModel(robot, np.zeros(N_POE_PARAMS), fit.world_T_base, registration, fit.errors)
    else:
        layout = paper_layout(robot)
        fit = fit_poe_positions(layout_twists(robot, layout), a, p, fit_base=True)
        assert fit.world_T_base is not None  # fit_base
        model = PoeErrorModel(robot, fit.x, fit.world_T_base, registration, layout=layout)
    residual = (model.predict_tcp_mm(a) - p).reshape(-1)
    kept = tuple(fit.names[i] for i in fit.report.identifiable_index)
    jac = model.parameter_jacobian(kept, np.zeros(len(kept)), Query(a)).reshape(-1, len(kept))
    if jac.shape[0] > jac.shape[1]:
        # the base parameters are increments about the fitted frame: value 0
        values = np.array([fit.theta[fit.names.index(n)] if n not in BASE_NAMES else 0.0 for n in kept])
        model.uncertainty = ParameterCovariance.of_fit(kept, values, jac, residual)
    rms = float(np.sqrt(np.mean(np.sum(residual.reshape(-1, 3) ** 2, axis=1))))
    return PoeErrorFit(model, fit, rms)


def fit_poe_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """The POE calibration: a twist error per joint, the tool offset and the base frame
    (``poe``), or seed 002's errors Δl, Δθ and the base frame (``poe:paper``)."""
    _, chosen, reg = registered_start(robot, rows.a_deg, rows.xyz_mm, options.frame)
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


KIND = ModelKind(
    "poe",
    "product-of-exponentials calibration: a twist error per joint, tool offset, base frame;"
    " poe:paper seed 002's dl1..dl6, dtheta1..dtheta6 and base frame",
    PoeErrorModel,
    fit_poe_kind,
    lambda spec: 12 + 6 if spec.paper else N_TWIST_PARAMS + 6,
    option_words=("paper",),
)
