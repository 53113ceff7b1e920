"""Kinematic parameters as arrays, the identification parameter vector, and axis ↔ DH conversion.

Convention (written once here and in the robot file's header), for joint i = 1..6::

    q_i = sign_i * A_i                            (A_i: controller axis value, deg; q_i in rad)
    theta_i = q_i + offset_i                      (offset_i: a calibrated parameter)
    T_{i-1,i} = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)
    world_T_tcp = world_T_base · T_01 · … · T_56 · Tz/Tx/Ty(tool_xyz)

Lengths are mm, angles inside the numerics are rad. ``world`` is the frame the TCP is measured in:
the robot base frame for a nominal twin (``world_T_base`` = identity), the tracker's frame once
registered.

The identification parameter vector has 39 entries (:data:`PARAM_NAMES`): for each joint
``theta, d, a, alpha, beta`` (rad, mm, mm, rad, rad), then the base frame ``base_x, base_y, base_z``
(mm) and ``base_rx, base_ry, base_rz`` (rad, small rotations about the world axes applied on the
left), then ``tool_x, tool_y, tool_z`` (mm, in the flange frame). :meth:`KinematicParams.apply`
adds such a vector; the identification Jacobian is the derivative of the TCP with respect to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.so3 import matrix_to_rotvec, rotvec_to_matrix
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "BASE_SLICE",
    "JOINT_PARAM_KINDS",
    "N_PARAMS",
    "PARAM_NAMES",
    "TOOL_SLICE",
    "KinematicParams",
    "as_six_columns",
    "axes_deg_to_q_rad",
    "joint_param_index",
    "q_rad_to_axes_deg",
]

JOINT_PARAM_KINDS = ("theta", "d", "a", "alpha", "beta")
PARAM_NAMES: tuple[str, ...] = (
    *(f"{kind}{j}" for j in range(1, 7) for kind in JOINT_PARAM_KINDS),
    "base_x",
    "base_y",
    "base_z",
    "base_rx",
    "base_ry",
    "base_rz",
    "tool_x",
    "tool_y",
    "tool_z",
)
N_PARAMS = len(PARAM_NAMES)
BASE_SLICE = slice(30, 36)
TOOL_SLICE = slice(36, 39)


def joint_param_index(kind: str, joint: int) -> int:
    """Index in the parameter vector of ``kind`` (theta, d, a, alpha, beta) of joint 1..6."""
    return (joint - 1) * len(JOINT_PARAM_KINDS) + JOINT_PARAM_KINDS.index(kind)


@dataclass(frozen=True, slots=True)
class KinematicParams:
    """One robot's kinematic parameters, in arrays (rad and mm)."""

    theta_offset_rad: NDArray[np.float64]
    d_mm: NDArray[np.float64]
    a_mm: NDArray[np.float64]
    alpha_rad: NDArray[np.float64]
    beta_rad: NDArray[np.float64]
    sign: NDArray[np.float64]
    tool_xyz_mm: NDArray[np.float64]
    world_T_base: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))

    @classmethod
    def from_robot(cls, robot: RobotDescription) -> KinematicParams:
        joints = robot.joints
        return cls(
            theta_offset_rad=np.deg2rad([j.offset_deg for j in joints]),
            d_mm=np.array([j.d_mm for j in joints], dtype=float),
            a_mm=np.array([j.a_mm for j in joints], dtype=float),
            alpha_rad=np.deg2rad([j.alpha_deg for j in joints]),
            beta_rad=np.deg2rad([j.beta_deg for j in joints]),
            sign=np.array([j.sign for j in joints], dtype=float),
            tool_xyz_mm=np.array(robot.tool_xyz_mm, dtype=float),
        )

    def joint_table(self) -> NDArray[np.float64]:
        """(6, 5) table of theta offset (rad), d, a (mm), alpha, beta (rad)."""
        return np.stack([self.theta_offset_rad, self.d_mm, self.a_mm, self.alpha_rad, self.beta_rad], axis=1)

    def with_joint_table(self, table: NDArray[np.float64]) -> KinematicParams:
        """These parameters with the joint geometry of a (6, 5) :meth:`joint_table` (copied)."""
        return replace(
            self,
            theta_offset_rad=table[:, 0].copy(),
            d_mm=table[:, 1].copy(),
            a_mm=table[:, 2].copy(),
            alpha_rad=table[:, 3].copy(),
            beta_rad=table[:, 4].copy(),
        )

    def apply(self, dx: NDArray[np.float64]) -> KinematicParams:
        """Parameters after adding an identification vector ``dx`` (layout of :data:`PARAM_NAMES`)."""
        dx = np.asarray(dx, dtype=float)
        if dx.shape != (N_PARAMS,):
            raise ValueError(f"parameter vector must have shape ({N_PARAMS},), got {dx.shape}")
        table = self.joint_table() + dx[:30].reshape(6, 5)
        delta = np.eye(4)
        delta[:3, :3] = rotvec_to_matrix(dx[33:36])
        delta[:3, 3] = dx[30:33]
        return replace(
            self.with_joint_table(table),
            tool_xyz_mm=self.tool_xyz_mm + dx[TOOL_SLICE],
            world_T_base=delta @ self.world_T_base,
        )

    def with_base(self, world_T_base: NDArray[np.float64]) -> KinematicParams:
        return replace(self, world_T_base=np.array(world_T_base, dtype=float))

    def difference(self, other: KinematicParams) -> NDArray[np.float64]:
        """The vector ``dx`` with ``other.apply(dx) ≈ self`` (exact for the joint and tool entries)."""
        dx = np.zeros(N_PARAMS)
        dx[:30] = (self.joint_table() - other.joint_table()).reshape(30)
        delta = self.world_T_base @ np.linalg.inv(other.world_T_base)
        dx[30:33] = delta[:3, 3]
        dx[33:36] = matrix_to_rotvec(delta[:3, :3])
        dx[TOOL_SLICE] = self.tool_xyz_mm - other.tool_xyz_mm
        return dx


def as_six_columns(value: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    """``value`` as an (n, 6) float array, one per joint (one pose may be given as (6,));
    another shape is a ValueError naming ``what`` and the shape given."""
    out = np.asarray(value, dtype=float)
    if out.ndim == 1:
        out = out[None, :]
    if out.ndim != 2 or out.shape[1] != 6:
        raise ValueError(f"{what} must have shape (n, 6), got {np.shape(value)}")
    return out


def axes_deg_to_q_rad(a_deg: NDArray[np.float64], sign: NDArray[np.float64]) -> NDArray[np.float64]:
    """Controller axis values (…, 6) in deg → joint angles q (…, 6) in rad, in DH sign.

    The DH angle is ``theta = q + theta_offset``; the offset belongs to the kinematic parameters
    (it is calibrated), the sign to the robot.
    """
    return sign * np.deg2rad(a_deg)


def q_rad_to_axes_deg(q_rad: NDArray[np.float64], sign: NDArray[np.float64]) -> NDArray[np.float64]:
    """Joint angles q (…, 6) in rad, DH sign → controller axis values (…, 6) in deg."""
    return np.rad2deg(q_rad) * sign
