"""The ``nominal`` kind: the robot description's geometry, nothing fitted but the frame.

On base-frame data the model is the description itself; on tracker data only the base frame is
registered (the rigid fit of :mod:`comp_daemon.estimation.registration`). It is the reference every
other kind is compared with.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.base import ErrorModel, Query, StoredModel
from comp_daemon.models.fitting import FitOptions, FittedModel, ModelSpec, rms_mm
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.kinematic import registered_start
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["KIND", "NominalModel", "fit_nominal_kind"]


class NominalModel(ErrorModel):
    """The robot description's nominal geometry in the frame ``world_T_base``."""

    kind: ClassVar[str] = "nominal"

    def __init__(self, robot: RobotDescription, registration: NDArray[np.float64] | None = None) -> None:
        self.robot = robot
        self.registration = np.eye(4) if registration is None else np.array(registration, dtype=float)
        self.world_T_base = self.registration
        self._params = KinematicParams.from_robot(robot).with_base(self.world_T_base)

    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        return tcp_position_mm(self._params, axes_deg_to_q_rad(query.a, self._params.sign))

    def ik_params(self) -> KinematicParams:
        return self._params

    def to_payload(self) -> dict[str, Any]:
        return {}

    @classmethod
    def from_stored(cls, stored: StoredModel) -> NominalModel:
        return cls(stored.robot, stored.registration)


def fit_nominal_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """The nominal geometry; on tracker data the base frame is registered (rigid fit), nothing else."""
    _, chosen, reg = registered_start(robot, rows.a_deg, rows.xyz_mm, options.frame)
    model = NominalModel(robot, reg)
    return FittedModel(model, chosen, {"kind": spec.kind, "rows": rows.n, "rms_mm": rms_mm(model, rows)})


KIND = ModelKind(
    "nominal",
    "the robot description's geometry; on tracker data only the base frame is registered",
    NominalModel,
    fit_nominal_kind,
    lambda spec: 6,
)
