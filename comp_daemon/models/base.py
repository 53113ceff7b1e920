"""The interface every error model offers.

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
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, Self

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import KinematicParams, as_six_columns
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "BaseLoader",
    "ErrorModel",
    "PredictionUncertainty",
    "Query",
    "StoredModel",
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


@dataclass(frozen=True, slots=True)
class Query:
    """The poses a prediction is asked at: the commanded axis values ``a`` (n, 6) and what else the
    models may use, the approach directions, the payload (kg; 0 when not given) and the temperature."""

    a: NDArray[np.float64]
    dir: NDArray[np.float64] | None = None
    payload_kg: NDArray[np.float64] | float = 0.0
    temp_c: NDArray[np.float64] | None = None

    @classmethod
    def of(
        cls,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> Query:
        """The query of :meth:`ErrorModel.predict_tcp_mm`'s arguments (one pose may be given as (6,))."""
        return cls(as_axes(a_deg), dir, 0.0 if payload_kg is None else payload_kg, temp_c)


#: rebuilds a stored model of any kind: ``(kind, robot, payload, order, registration) -> model``
BaseLoader = Callable[
    [str, RobotDescription, dict[str, Any], "int | None", NDArray[np.float64]], "ErrorModel"
]


@dataclass(frozen=True, slots=True)
class StoredModel:
    """A model as an artifact keeps it, read back for ``robot``: its content (``to_payload``), its
    order (Chebyshev) and the registration it was fitted after; ``base_loader`` rebuilds the model
    a stacked model stores inside it (the registry's
    :func:`~comp_daemon.models.registry.model_from_payload`, which passes itself)."""

    robot: RobotDescription
    payload: dict[str, Any]
    order: int | None
    registration: NDArray[np.float64]
    base_loader: BaseLoader | None = None


class PredictionUncertainty(Protocol):
    """What a model's ``uncertainty`` offers (:class:`comp_daemon.models.covariance.ParameterCovariance`)."""

    def std_mm(self, model: ErrorModel, query: Query) -> NDArray[np.float64]: ...

    def to_dict(self) -> dict[str, Any]: ...


class ErrorModel(ABC):
    """A fitted (or nominal) model of where the TCP really goes.

    A kind implements :meth:`tcp_mm` (the prediction at a :class:`Query`), :meth:`to_payload` and
    :meth:`from_stored`; :meth:`predict_tcp_mm`, :meth:`predict_std_mm` and :meth:`from_payload`
    are the doors every caller uses, written here once."""

    kind: ClassVar[str]
    robot: RobotDescription
    world_T_base: NDArray[np.float64]
    registration: NDArray[np.float64]
    uncertainty: PredictionUncertainty | None = None

    def predict_tcp_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """(n, 3) predicted TCP (mm, measurement frame) at commanded axis values ``a_deg`` (n, 6)."""
        return self.tcp_mm(Query.of(a_deg, dir, payload_kg, temp_c))

    def predict_std_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64] | None:
        """(n, 3) 1-σ uncertainty (mm) of :meth:`predict_tcp_mm` at ``a_deg``, or None (module docstring)."""
        return self.std_mm(Query.of(a_deg, dir, payload_kg, temp_c))

    @abstractmethod
    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        """(n, 3) predicted TCP (mm, measurement frame) at the query's poses."""

    def std_mm(self, query: Query) -> NDArray[np.float64] | None:
        """(n, 3) 1-σ uncertainty (mm) of :meth:`tcp_mm`: the ``uncertainty``'s, None without one."""
        if self.uncertainty is None:
            return None
        return self.uncertainty.std_mm(self, query)

    def parameter_jacobian(
        self, names: Sequence[str], values: NDArray[np.float64], query: Query
    ) -> NDArray[np.float64]:
        """(n, 3, p) derivative of the TCP at the query's poses w.r.t. the fitted parameters
        ``names`` at ``values`` (as the fit iterated them): what a parameter covariance is
        propagated through (:mod:`comp_daemon.models.covariance`)."""
        raise ValueError(f"no parameter covariance for a {self.kind} model")

    def ik_params(self) -> KinematicParams:
        """Kinematic parameters (measurement frame) the compensation inverts the axes with."""
        return KinematicParams.from_robot(self.robot).with_base(self.world_T_base)

    @abstractmethod
    def to_payload(self) -> dict[str, Any]:
        """The model's own content (parameters, coefficients) as JSON-ready values."""

    @classmethod
    def from_payload(
        cls,
        robot: RobotDescription,
        payload: dict[str, Any],
        order: int | None,
        registration: NDArray[np.float64],
    ) -> Self:
        """The model back from :meth:`to_payload`'s content."""
        return cls.from_stored(StoredModel(robot, payload, order, registration))

    @classmethod
    @abstractmethod
    def from_stored(cls, stored: StoredModel) -> Self:
        """The model back from an artifact's record of it (:meth:`from_payload`)."""

    @property
    def order(self) -> int | None:
        return None
