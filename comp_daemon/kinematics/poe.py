"""Product-of-exponentials (POE) kinematics and the Δl/Δθ error model (seed 002, spec A.1–A.2).

Convention, written once here. A revolute joint i has the unit axis ``omega[i]`` and an axis point
``point_mm[i]`` in the robot base frame at the zero pose (all axis values A = 0). With the joint
angle ``theta_i = A_i`` (rad) the TCP is::

    base_T_flange(A) = exp([xi_1] theta_1) ··· exp([xi_6] theta_6) · base_T_flange0
    exp([xi] theta) = [[R, (I − R)·q], [0, 1]],  R = I + sin θ [ω]× + (1 − cos θ) [ω]×²
    p_tcp = base_T_flange(A) · [tool_xyz_mm, 1]

:meth:`PoeModel.from_robot` builds the twists from a robot description by walking its DH chain at
A = 0: ``omega_i = sign_i · z_{i−1}``, ``q_i = origin_{i−1}``, ``base_T_flange0 = T_06``. The result
equals the MDH model of :mod:`comp_daemon.kinematics.forward` at nominal.

**Error model** (12 parameters, :data:`POE_PARAM_NAMES`): ``dl1..dl6`` (mm) and ``dtheta1..dtheta6``
(rad). The joint points and the flange origin are a chain of *segments*, each a length along a fixed
direction (at the zero pose) that moves every point from its ``first_point`` on (points 0..5 are the
joint points q1..q6, point 6 the flange origin). ``dl_s`` lengthens segment s; segments beyond the
sixth are fixed. ``dtheta_i`` adds to joint i's angle. The axis directions stay nominal (the seed drops
Δω). :func:`irb120_table1` is the seed's layout for the ABB IRB 120 (Table 1 and spec A.2: segments
187 z, 103 z, 270 z, 70 z, 134 x, 168 x, then 72 x fixed); :meth:`PoeModel.from_robot` uses one segment
per joint, from the previous joint point (or the base origin) to the joint's point, and the flange
segment fixed.

The derivative of the TCP with respect to ``dl_s`` is ``R_{<f}·dir_s`` (the rotation of the joints
before the segment's first moved point; the contributions of the moved joint points telescope), and
with respect to ``dtheta_i`` the spatial twist ``omega'_i × (p − q'_i)``.

:func:`poe_ik` solves the inverse kinematics of a model with errors (position and flange
orientation, Gauss–Newton from a nearby seed): the compensation step after a calibration.

Frames and units live in the names: ``a_deg`` axis values in degrees (batch (n, 6)), ``x`` error
vectors ((12,) or one per pose, (n, 12)), positions in mm in the robot base frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.inverse import orientation_error_rad
from comp_daemon.kinematics.params import as_six_columns
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "N_POE_PARAMS",
    "POE_PARAM_NAMES",
    "PoeChain",
    "PoeModel",
    "irb120_table1",
    "poe_chain",
    "poe_error_jacobian",
    "poe_flange_pose",
    "poe_ik",
    "poe_tcp_position_mm",
]

POE_PARAM_NAMES: tuple[str, ...] = (
    *(f"dl{i}" for i in range(1, 7)),
    *(f"dtheta{i}" for i in range(1, 7)),
)
N_POE_PARAMS = len(POE_PARAM_NAMES)
_ZERO_LENGTH_MM = 1e-9


@dataclass(frozen=True, slots=True)
class PoeModel:
    """Twists at the zero pose, the zero-pose flange frame, the tool and the segment chain.

    ``segment_dir`` (m, 3) unit directions, ``segment_length_mm`` (m,), ``segment_first_point`` (m,)
    in 0..6; the first six segments carry ``dl1..dl6``. ``anchor_mm`` (7, 3) is the part of each point
    (q1..q6, flange origin) that no segment expresses, so that point j is
    ``anchor_mm[j] + Σ_{s: first_point_s ≤ j} length_s·dir_s``.
    """

    omega: NDArray[np.float64]  # (6, 3)
    point_mm: NDArray[np.float64]  # (6, 3)
    base_R_flange0: NDArray[np.float64]  # (3, 3)
    flange0_mm: NDArray[np.float64]  # (3,)
    tool_xyz_mm: NDArray[np.float64]  # (3,)
    segment_dir: NDArray[np.float64]  # (m, 3)
    segment_length_mm: NDArray[np.float64]  # (m,)
    segment_first_point: NDArray[np.intp]  # (m,)
    anchor_mm: NDArray[np.float64]  # (7, 3)

    @classmethod
    def from_robot(cls, robot: RobotDescription) -> PoeModel:
        """Twists from the DH chain of ``robot`` at A = 0; one segment per joint point (module docstring)."""
        frames = _dh_frames_at_zero(robot)
        omega = np.array([j.sign * frames[i][:3, 2] for i, j in enumerate(robot.joints)])
        points = np.array([frames[i][:3, 3] for i in range(6)])
        flange = frames[6]
        all_points = np.vstack([points, flange[:3, 3]])
        prev = np.vstack([np.zeros(3), all_points[:-1]])
        seg = all_points - prev
        length = np.linalg.norm(seg, axis=1)
        direction = np.where(
            (length > _ZERO_LENGTH_MM)[:, None],
            seg / np.where(length > _ZERO_LENGTH_MM, length, 1.0)[:, None],
            np.vstack([omega, omega[-1:]]),
        )
        return cls(
            omega=omega,
            point_mm=points,
            base_R_flange0=flange[:3, :3].copy(),
            flange0_mm=flange[:3, 3].copy(),
            tool_xyz_mm=np.array(robot.tool_xyz_mm, dtype=float),
            segment_dir=direction,
            segment_length_mm=length,
            segment_first_point=np.arange(7, dtype=np.intp),
            anchor_mm=np.zeros((7, 3)),
        )

    def with_tool(self, tool_xyz_mm: NDArray[np.float64] | tuple[float, float, float]) -> PoeModel:
        """The same robot with another TCP offset in the flange frame (mm)."""
        return replace(self, tool_xyz_mm=np.array(tool_xyz_mm, dtype=float))

    def points_mm(self, dl_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """(n, 7, 3) joint points q1..q6 and flange origin for length errors ``dl_mm`` (n, 6)."""
        length = np.broadcast_to(self.segment_length_mm, (dl_mm.shape[0], self.segment_length_mm.size)).copy()
        length[:, :6] += dl_mm
        moves = (self.segment_first_point[:, None] <= np.arange(7)[None, :]).astype(float)  # (m, 7)
        per_point = np.einsum("nm,mj->njm", length, moves)  # (n, 7, m) length reaching point j
        return self.anchor_mm[None] + per_point @ self.segment_dir


def irb120_table1(robot: RobotDescription) -> PoeModel:
    """The seed-002 layout of the ABB IRB 120: Table 1 twists and the segment table of spec A.2.

    The zero-pose flange frame and the tool come from ``robot`` (its DH chain at A = 0), which must be
    the IRB 120 (flange origin (374, 0, 630) mm at the zero pose).
    """
    flange = _dh_frames_at_zero(robot)[6]
    if not np.allclose(flange[:3, 3], [374.0, 0.0, 630.0], atol=1e-6):
        raise ValueError(
            f"{robot.name}: zero-pose flange at {flange[:3, 3]}, not the IRB 120's (374, 0, 630)"
        )
    ez, ex = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    return PoeModel(
        omega=np.array([ez, [0, 1, 0], [0, 1, 0], ex, [0, 1, 0], ex], dtype=float),
        point_mm=np.array(
            [[0, 0, 187], [0, 0, 290], [0, 0, 560], [134, 0, 630], [302, 0, 630], [374, 0, 630]], dtype=float
        ),
        base_R_flange0=flange[:3, :3].copy(),
        flange0_mm=flange[:3, 3].copy(),
        tool_xyz_mm=np.array(robot.tool_xyz_mm, dtype=float),
        segment_dir=np.array([ez, ez, ez, ez, ex, ex, ex]),
        segment_length_mm=np.array([187.0, 103.0, 270.0, 70.0, 134.0, 168.0, 72.0]),
        segment_first_point=np.array([0, 1, 2, 3, 3, 4, 5], dtype=np.intp),
        anchor_mm=np.zeros((7, 3)),
    )


def _dh_frames_at_zero(robot: RobotDescription) -> list[NDArray[np.float64]]:
    """Frames 0..6 of the MDH chain at A = 0 (theta = offset), base frame = frame 0."""
    frames = [np.eye(4)]
    for j in robot.joints:
        th, al, be = np.deg2rad(j.offset_deg), np.deg2rad(j.alpha_deg), np.deg2rad(j.beta_deg)
        rz = np.array(
            [[np.cos(th), -np.sin(th), 0, 0], [np.sin(th), np.cos(th), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        )
        tz = np.eye(4)
        tz[2, 3] = j.d_mm
        tx = np.eye(4)
        tx[0, 3] = j.a_mm
        rx = np.array(
            [[1, 0, 0, 0], [0, np.cos(al), -np.sin(al), 0], [0, np.sin(al), np.cos(al), 0], [0, 0, 0, 1]]
        )
        ry = np.array(
            [[np.cos(be), 0, np.sin(be), 0], [0, 1, 0, 0], [-np.sin(be), 0, np.cos(be), 0], [0, 0, 0, 1]]
        )
        frames.append(frames[-1] @ rz @ tz @ tx @ rx @ ry)
    return frames


@dataclass(frozen=True, slots=True)
class PoeChain:
    """A batch of POE evaluations with the partial products kept (for Jacobians).

    ``R_before[:, i]`` is the rotation of joints 1..i (i = 0..6; index 0 the identity),
    ``axis[:, i]`` / ``axis_point_mm[:, i]`` joint i+1's axis and a point on it in the current pose.
    """

    base_T_flange: NDArray[np.float64]  # (n, 4, 4)
    tcp_mm: NDArray[np.float64]  # (n, 3)
    R_before: NDArray[np.float64]  # (n, 7, 3, 3)
    axis: NDArray[np.float64]  # (n, 6, 3)
    axis_point_mm: NDArray[np.float64]  # (n, 6, 3)


def _batch(
    a_deg: NDArray[np.float64], x: NDArray[np.float64] | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    a = as_six_columns(a_deg, "axis values")
    xx = np.zeros(N_POE_PARAMS) if x is None else np.asarray(x, dtype=float)
    if xx.shape[-1] != N_POE_PARAMS or xx.ndim > 2:
        raise ValueError(f"error vector must have shape (12,) or (n, 12), got {xx.shape}")
    return a, np.array(np.broadcast_to(xx, (a.shape[0], N_POE_PARAMS)))


def poe_chain(model: PoeModel, a_deg: NDArray[np.float64], x: NDArray[np.float64] | None = None) -> PoeChain:
    """POE forward kinematics of n poses (axis values in deg) with error vector(s) ``x``."""
    a, xx = _batch(a_deg, x)
    n = a.shape[0]
    theta = np.deg2rad(a) + xx[:, 6:]
    pts = model.points_mm(xx[:, :6])  # (n, 7, 3)
    w = model.omega
    rot = np.empty((n, 3, 3))
    rot[:] = np.eye(3)
    trans = np.zeros((n, 3))
    r_before = np.empty((n, 7, 3, 3))
    r_before[:, 0] = rot
    axis = np.empty((n, 6, 3))
    axis_pt = np.empty((n, 6, 3))
    eye3 = np.eye(3)
    for i in range(6):
        # 3×3 blocks and vectors: batched 4×4 products are several times slower
        k = np.array([[0.0, -w[i, 2], w[i, 1]], [w[i, 2], 0.0, -w[i, 0]], [-w[i, 1], w[i, 0], 0.0]])
        s, c = np.sin(theta[:, i]), np.cos(theta[:, i])
        r_i = eye3 + s[:, None, None] * k + (1.0 - c)[:, None, None] * (k @ k)
        t_i = pts[:, i] - (r_i @ pts[:, i, :, None])[..., 0]
        axis[:, i] = rot @ w[i]
        axis_pt[:, i] = (rot @ pts[:, i, :, None])[..., 0] + trans
        trans = (rot @ t_i[..., None])[..., 0] + trans
        rot = rot @ r_i
        r_before[:, i + 1] = rot
    flange = np.zeros((n, 4, 4))
    flange[:, :3, :3] = rot @ model.base_R_flange0
    flange[:, :3, 3] = (rot @ pts[:, 6, :, None])[..., 0] + trans
    flange[:, 3, 3] = 1.0
    tcp = flange[:, :3, :3] @ model.tool_xyz_mm + flange[:, :3, 3]
    return PoeChain(base_T_flange=flange, tcp_mm=tcp, R_before=r_before, axis=axis, axis_point_mm=axis_pt)


def poe_flange_pose(
    model: PoeModel, a_deg: NDArray[np.float64], x: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """(n, 4, 4) base_T_flange."""
    return poe_chain(model, a_deg, x).base_T_flange


def poe_tcp_position_mm(
    model: PoeModel, a_deg: NDArray[np.float64], x: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """(n, 3) TCP position in the robot base frame, mm."""
    return poe_chain(model, a_deg, x).tcp_mm


def poe_error_jacobian(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    x: NDArray[np.float64] | None = None,
    ch: PoeChain | None = None,
) -> NDArray[np.float64]:
    """(n, 3, 12) derivative of the TCP (mm) w.r.t. (dl1..dl6 [mm], dtheta1..dtheta6 [rad])."""
    ch = ch if ch is not None else poe_chain(model, a_deg, x)
    n = ch.tcp_mm.shape[0]
    jac = np.empty((n, 3, N_POE_PARAMS))
    first = model.segment_first_point[:6]
    jac[:, :, :6] = np.einsum("nsij,sj->nis", ch.R_before[:, first], model.segment_dir[:6])
    jac[:, :, 6:] = np.cross(ch.axis, ch.tcp_mm[:, None, :] - ch.axis_point_mm).transpose(0, 2, 1)
    return jac


def poe_ik(
    model: PoeModel,
    target_p_mm: NDArray[np.float64],
    target_R: NDArray[np.float64],
    seed_a_deg: NDArray[np.float64],
    x: NDArray[np.float64] | None = None,
    *,
    max_iter: int = 50,
    tol_mm: float = 1e-9,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Axis values (n, 6) in deg that put the TCP of the model with errors ``x`` at ``target_p_mm``
    (n, 3) with flange orientation ``target_R`` (n, 3, 3); Gauss–Newton from ``seed_a_deg`` (the
    nominal solution), no joint limits. Returns the answer and the remaining position error (mm)."""
    a = np.array(np.broadcast_to(seed_a_deg, (np.shape(target_p_mm)[0], 6)), dtype=float)
    lever_mm = 1000.0  # orientation residual in mm at this lever, as the MDH IK does
    err_p = np.full(a.shape[0], np.inf)
    for _ in range(max_iter):
        ch = poe_chain(model, a, x)
        e_p = target_p_mm - ch.tcp_mm
        e_r = orientation_error_rad(ch.base_T_flange[:, :3, :3], target_R)
        err_p = np.linalg.norm(e_p, axis=1)
        if err_p.max() < tol_mm and np.abs(e_r).max() < tol_mm / lever_mm:
            break
        lin = np.cross(ch.axis, ch.tcp_mm[:, None, :] - ch.axis_point_mm)  # (n, 6, 3) per joint
        jac = np.concatenate([lin, ch.axis * lever_mm], axis=2).transpose(0, 2, 1)  # (n, 6, 6)
        err = np.concatenate([e_p, e_r * lever_mm], axis=1)
        d_theta = np.linalg.solve(jac, err[..., None])[..., 0]
        a = a + np.rad2deg(d_theta)
    return a, err_p
