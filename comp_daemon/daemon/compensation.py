"""Target compensation by the store's active model, for the executor (runs in a worker thread).

A target (:class:`comp_daemon.data.target.Target`, a row of a target file, ``docs/data-format.md``)
gives either the axis values ``a1..a6`` of the nominal program (deg) or the wanted TCP
``tx, ty, tz`` (mm, robot base frame) with an optional orientation ``ta, tb, tc`` (deg, KUKA A, B,
C of the tool frame), and optionally ``payload_kg``. The wanted TCP of an axis-value request is its
nominal forward kinematics.

The active model (loaded from its artifact, cached by model id) then gives the commanded axis
values whose *predicted* TCP is the wanted one (:func:`comp_daemon.models.compensation.compensate`,
model + inverse kinematics iterated, seeded from the nominal axis values or the robot's current
ones). The loop target of each joint with a grating is its commanded angle: after arrival the loop
drives the grating angles there, taking out backlash and whatever else the joint does differently
from its motor (seed 000, step 5). Approach directions passed to the model are those the motion
will have on the joints without gratings; on grating joints the direction is left unknown (0),
since the loop removes the direction-dependent part there.

``mapping`` (``[compensation] mapping``) chooses how the compensated target becomes axis values:
the six-axis inverse kinematics (default) or seed 000's mapping onto joints 1–3 with the wrist of
the nominal solution (:mod:`comp_daemon.models.compensation`). The target's outcome ``info`` holds
the nominal solution, the predicted residual, the iterations, the mapping and, for a model with an
uncertainty, ``predicted_sigma_mm``: the 3-D 1-σ uncertainty of the model's TCP prediction at the
commanded axes (``|σ|`` of the x, y, z standard deviations; none for the nominal model). The
executor hands it, with the model id, to the store with the target's move to ``moving``; the API's
target output reads it from that event.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from comp_daemon.common.logs import get_logger
from comp_daemon.data.target import Target
from comp_daemon.kinematics.inverse import UnreachableTargetError
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc
from comp_daemon.models import artifact as artifacts
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.compensation import (
    DEFAULT_LIMITS,
    MAPPINGS,
    CompensationLimits,
    JointMapping,
    compensate,
    nominal_targets,
)
from comp_daemon.robot.description import RobotDescription
from comp_daemon.rt.executor import CompensatedTarget, CompensationError, ModelMissingError
from comp_daemon.service.store import Store

__all__ = ["ActiveModelCompensator", "model_from_artifact"]

log = get_logger(__name__)


def model_from_artifact(artifact: Mapping[str, Any], robot: RobotDescription, where: str) -> ErrorModel:
    """The model of a stored artifact (:func:`comp_daemon.models.artifact.model_from_artifact`: every
    kind of the model registry); a document that cannot be used is a :class:`ModelMissingError`."""
    try:
        return artifacts.model_from_artifact(artifact, robot, where)
    except artifacts.ModelArtifactError as exc:
        raise ModelMissingError(str(exc)) from None


class ActiveModelCompensator:
    """A :data:`comp_daemon.rt.executor.Compensator` over the store's active model."""

    def __init__(
        self,
        store: Store,
        robot: RobotDescription,
        joints: Sequence[int],
        *,
        current_axes: Callable[[], Sequence[float] | None] | None = None,
        limits: CompensationLimits = DEFAULT_LIMITS,
        mapping: JointMapping = "six-axis",
    ) -> None:
        if mapping not in MAPPINGS:
            raise ValueError(f"mapping must be one of {', '.join(MAPPINGS)}, got {mapping!r}")
        self.store = store
        self.limits = limits  # the [compensation] settings: axis change, wrist, sampled region
        self.mapping: JointMapping = mapping  # [compensation] mapping: six-axis IK or seed 000's
        self.robot = robot
        self.joints = tuple(joints)  # 0-based indices of the joints with gratings
        self.current_axes = current_axes
        self._cache: tuple[int, ErrorModel] | None = None
        self._lock = threading.Lock()

    def model(self) -> tuple[int, ErrorModel]:
        record = self.store.active_model(with_artifact=False)
        if record is None:
            raise ModelMissingError("no model is active")
        with self._lock:
            if self._cache is not None and self._cache[0] == record.id:
                return self._cache
        full = self.store.get_model(record.id, with_artifact=True)
        assert full.artifact is not None
        model = model_from_artifact(full.artifact, self.robot, f"model {record.id}")
        with self._lock:
            self._cache = (record.id, model)
        return record.id, model

    def __call__(self, target: Target) -> CompensatedTarget:
        model_id, model = self.model()
        payload = target.payload_kg
        current = self.current_axes() if self.current_axes is not None else None
        seed: np.ndarray | None
        r_wanted: np.ndarray | None
        if target.axes_deg is not None:
            a_nominal = np.array([target.axes_deg])
            p_wanted, r_wanted = nominal_targets(model, a_nominal)
            seed = a_nominal
        else:
            assert target.tcp_mm is not None  # a Target has exactly one form
            p_wanted = np.array([target.tcp_mm])
            r_wanted = None
            if target.abc_deg is not None:
                r_wanted = flange_rotation_of_tool_abc(np.array([target.abc_deg]))
            seed = None if current is None else np.asarray(current, dtype=float)[None, :]
        direction = None
        if current is not None and seed is not None:
            direction = np.sign(seed - np.asarray(current, dtype=float)[None, :])
            direction[:, list(self.joints)] = 0.0
        try:
            res = compensate(
                model,
                p_wanted,
                r_wanted,
                a_seed_deg=seed,
                dir=direction,
                payload_kg=payload,
                limits=self.limits,
                mapping=self.mapping,
            )
        except UnreachableTargetError as exc:
            raise CompensationError(str(exc)) from None
        if not res.converged:
            raise CompensationError(
                f"the compensation did not converge (predicted error {float(res.residual_mm[0]):.4f} mm "
                f"after {res.iterations} iterations)"
            )
        commanded = tuple(float(v) for v in res.a_deg[0])
        limits = self.robot.axis_limits_deg
        for j, v in enumerate(commanded):
            if not limits[j, 0] <= v <= limits[j, 1]:
                raise CompensationError(f"the compensated A{j + 1} = {v:.4f} deg is outside the axis limits")
        info: dict[str, Any] = {
            "uncompensated_deg": [float(v) for v in res.a_uncompensated_deg[0]],
            "predicted_residual_mm": float(res.residual_mm[0]),
            "iterations": res.iterations,
            "mapping": self.mapping,
        }
        sigma = model.predict_std_mm(res.a_deg, direction, payload)
        if sigma is not None:  # 3-D 1-σ uncertainty of the model's TCP at the commanded axes
            info["predicted_sigma_mm"] = float(np.linalg.norm(sigma[0]))
        return CompensatedTarget(commanded, tuple(commanded[j] for j in self.joints), model_id, info)
