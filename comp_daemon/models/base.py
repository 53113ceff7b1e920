"""The interface every error model offers, and the nominal model.

An error model predicts where the TCP really is (mm, in the measurement frame ``world``) when the
controller is commanded to axis values ``a_deg`` (n, 6; controller convention), optionally with the
approach directions ``dir`` (n, 6; −1/+1, 0 unknown), the payload (kg) and the temperature (°C):
``predict_tcp_mm(a_deg, dir, payload_kg, temp_c) -> (n, 3)``. Models that ignore an input accept it.

``registration`` (4, 4) is the robot base frame as registered in the measurement frame before any fit
(identity when the data are in the robot base frame; the rigid fit of
:mod:`comp_daemon.estimation.registration` for a tracker frame): it maps targets given in the robot base
frame into the measurement frame. ``world_T_base`` is the model's own (possibly calibrated) base frame.
``ik_params()`` are the kinematic parameters (measurement frame) that the compensation uses to invert
the commanded axes.

``predict_std_mm(a_deg, dir, payload_kg, temp_c) -> (n, 3) | None`` is the 1-σ uncertainty (mm,
per coordinate) of those predictions where the model has one: the parameter covariance of a
parametric fit propagated through its Jacobian (``uncertainty``, a
:class:`comp_daemon.models.covariance.ParameterCovariance` set by the fit or the artifact
loader), or a kriging model's kriging variance; None otherwise.

The nominal model is the robot description's geometry, nothing fitted but the frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, as_six_columns, axes_deg_to_q_rad
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "ErrorModel",
    "NominalModel",
    "PredictionUncertainty",
    "approach_directions",
    "as_axes",
    "finite_array",
    "further_targets",
    "measured_positions",
    "uses_approach_directions",
]


def uses_approach_directions(model: object) -> bool:
    """Whether ``model``'s prediction depends on the approach directions ``dir``: a backlash it
    kept (non-zero), or a direction-aware kriging distance, on the model or the base it stacks on."""
    m: object | None = model
    while m is not None:
        effects = getattr(m, "effects", None)
        if effects is not None and np.any(getattr(effects, "backlash_deg", 0.0)):
            return True
        if getattr(m, "sample_dir", None) is not None:
            return True
        m = getattr(m, "base", None)
    return False


def as_axes(a_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """``a_deg`` as an (n, 6) float array (one pose may be given as (6,))."""
    return as_six_columns(a_deg, "axis values")


def approach_directions(dir: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
    """The (n, 6) approach directions of ``n`` poses (one row may be given as (6,); None: zeros,
    unknown); another shape is a ValueError naming ``dir``."""
    if dir is None:
        return np.zeros((n, 6))
    d = np.asarray(dir, dtype=float)
    if d.ndim == 1:
        d = d[None, :]
    if d.shape != (n, 6):
        raise ValueError(f"dir: expected shape ({n}, 6) like the axis values, got {d.shape}")
    return d


def finite_array(value: Any, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    """``value`` as a finite float array of ``shape`` (ValueError naming ``name``)."""
    out = np.array(value, dtype=float)
    if out.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name}: values must be finite")
    return out


def measured_positions(value: Any, n: int) -> NDArray[np.float64]:
    """The (n, 3) measured TCP positions of ``n`` rows, finite (a ValueError saying which is wrong)."""
    p = np.asarray(value, dtype=float)
    if p.shape != (n, 3):
        raise ValueError(f"measured positions must have shape ({n}, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("measured positions must be finite")
    return p


def further_targets(value: Any, n: int) -> NDArray[np.float64]:
    """The (n, K − 1, 3) measured positions of ``n`` rows' further targets (a ValueError naming the shape)."""
    more = np.asarray(value, dtype=float)
    if more.ndim != 3 or more.shape[0] != n or more.shape[2] != 3:
        raise ValueError(f"further targets must have shape ({n}, K - 1, 3), got {more.shape}")
    return more


class PredictionUncertainty(Protocol):
    """What a model's ``uncertainty`` offers (:class:`comp_daemon.models.covariance.ParameterCovariance`)."""

    def std_mm(
        self,
        model: ErrorModel,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]: ...

    def to_dict(self) -> dict[str, Any]: ...


class ErrorModel(ABC):
    """A fitted (or nominal) model of where the TCP really goes."""

    kind: ClassVar[str]
    robot: RobotDescription
    world_T_base: NDArray[np.float64]
    registration: NDArray[np.float64]
    uncertainty: PredictionUncertainty | None = None

    def predict_std_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64] | None:
        """(n, 3) 1-σ uncertainty (mm) of :meth:`predict_tcp_mm` at ``a_deg``, or None (module docstring)."""
        if self.uncertainty is None:
            return None
        return self.uncertainty.std_mm(self, as_axes(a_deg), dir, payload_kg, temp_c)

    @abstractmethod
    def predict_tcp_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """(n, 3) predicted TCP (mm, measurement frame) at commanded axis values ``a_deg`` (n, 6)."""

    def ik_params(self) -> KinematicParams:
        """Kinematic parameters (measurement frame) the compensation inverts the axes with."""
        return KinematicParams.from_robot(self.robot).with_base(self.world_T_base)

    @abstractmethod
    def to_payload(self) -> dict[str, Any]:
        """The model's own content (parameters, coefficients) as JSON-ready values."""

    @classmethod
    @abstractmethod
    def from_payload(
        cls,
        robot: RobotDescription,
        payload: dict[str, Any],
        order: int | None,
        registration: NDArray[np.float64],
    ) -> ErrorModel:
        """The model back from :meth:`to_payload`'s content."""

    @property
    def order(self) -> int | None:
        return None


class NominalModel(ErrorModel):
    """The robot description's nominal geometry in the frame ``world_T_base``."""

    kind: ClassVar[str] = "nominal"

    def __init__(self, robot: RobotDescription, registration: NDArray[np.float64] | None = None) -> None:
        self.robot = robot
        self.registration = np.eye(4) if registration is None else np.array(registration, dtype=float)
        self.world_T_base = self.registration
        self._params = KinematicParams.from_robot(robot).with_base(self.world_T_base)

    def predict_tcp_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        return tcp_position_mm(self._params, axes_deg_to_q_rad(as_axes(a_deg), self._params.sign))

    def ik_params(self) -> KinematicParams:
        return self._params

    def to_payload(self) -> dict[str, Any]:
        return {}

    @classmethod
    def from_payload(
        cls,
        robot: RobotDescription,
        payload: dict[str, Any],
        order: int | None,
        registration: NDArray[np.float64],
    ) -> NominalModel:
        return cls(robot, registration)
