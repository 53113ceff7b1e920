"""Batch forward kinematics, Jacobians and static gravity torques.

Every function takes ``q_rad`` of shape (n, 6) (joint angles in DH sign, see
:mod:`comp_daemon.kinematics.params`) and works on all n poses at once; a single pose is n = 1.
Frame names follow ``a_T_b`` (pose of b in a); ``world`` is the measurement frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, as_six_columns

__all__ = [
    "GRAVITY_MPS2",
    "Chain",
    "chain",
    "flange_pose",
    "geometric_jacobian",
    "gravity_torques_nm",
    "identification_jacobian",
    "position_jacobian_mm",
    "tcp_position_mm",
]

GRAVITY_MPS2 = 9.81


@dataclass(frozen=True, slots=True)
class Chain:
    """All frames of a batch of poses.

    ``world_T_frame[:, i]`` is frame i (0 = robot base, 6 = flange) in the world frame;
    ``x_prime[:, i]`` is the x axis of joint i+1 after ``Rz(theta)`` (the axis ``a`` and ``alpha``
    act along), ``y_beta[:, i]`` the y axis that ``beta`` turns about; ``tcp_mm`` the TCP in world.
    """

    world_T_frame: NDArray[np.float64]  # (n, 7, 4, 4)
    x_prime: NDArray[np.float64]  # (n, 6, 3)
    y_beta: NDArray[np.float64]  # (n, 6, 3)
    tcp_mm: NDArray[np.float64]  # (n, 3)


def _combine(out: NDArray[np.float64], terms: tuple[tuple[float, NDArray[np.float64]], ...]) -> None:
    """``out`` = Σ coefficient · row over ``terms``, in their order, without the terms whose
    coefficient is 0 and without multiplying by 1 (the same values, fewer passes over the rows)."""
    first = True
    for coef, row in terms:
        if coef == 0.0:
            continue
        if first:
            if coef == 1.0:
                out[...] = row
            else:
                np.multiply(row, coef, out=out)
            first = False
        elif coef == 1.0:
            out += row
        else:
            out += row * coef
    if first:
        out[...] = 0.0


def chain(params: KinematicParams, q_rad: NDArray[np.float64]) -> Chain:
    """Forward kinematics of n poses with every intermediate frame kept (for Jacobians)."""
    q = as_six_columns(q_rad, "joint angles")
    n = q.shape[0]
    theta = (q + params.theta_offset_rad).T  # (6, n)
    c, s = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(params.alpha_rad), np.sin(params.alpha_rad)
    cb, sb = np.cos(params.beta_rad), np.sin(params.beta_rad)
    # every frame as rows of n values, (7, 4, 4, n): each step of the chain works on whole rows;
    # axes[f, k, j] is component j of axis k (x, y, z) of frame f, origin[f, j] that of its origin
    stacked = np.empty((7, 4, 4, n))
    stacked[:, 3, :3] = 0.0
    stacked[:, 3, 3] = 1.0
    axes = stacked[:, :3, :3].transpose(0, 2, 1, 3)
    origin = stacked[:, :3, 3]
    base = np.asarray(params.world_T_base, dtype=float)
    stacked[0] = base[:, :, None]
    x_prime = np.empty((6, 3, n))
    y_beta = np.empty((6, 3, n))
    y_turned = np.empty((3, n))
    for i in range(6):
        # link i: rotation Rz(theta) M with M = Rx(alpha) Ry(beta), translation Rz(theta)·(a, 0, d);
        # the axes of Rz(theta) in the previous frame are x' = x c + y s, y' = −x s + y c, z
        x_axis, y_axis, z_axis = axes[i]
        xp = np.multiply(x_axis, c[i], out=x_prime[i])
        xp += y_axis * s[i]
        yp = np.multiply(y_axis, c[i], out=y_turned)
        yp -= x_axis * s[i]
        # the new axes: column k of (x', y', z) · M, element by element (no BLAS: a pose's frames do
        # not depend on the other poses of the batch); M's middle column is (0, cos α, sin α), the
        # axis beta turns about
        _combine(axes[i + 1, 0], ((cb[i], xp), (sa[i] * sb[i], yp), (-ca[i] * sb[i], z_axis)))
        _combine(y_beta[i], ((ca[i], yp), (sa[i], z_axis)))
        axes[i + 1, 1] = y_beta[i]
        _combine(axes[i + 1, 2], ((sb[i], xp), (-sa[i] * cb[i], yp), (ca[i] * cb[i], z_axis)))
        _combine(origin[i + 1], ((1.0, origin[i]), (params.a_mm[i], xp), (params.d_mm[i], z_axis)))
    tool = np.asarray(params.tool_xyz_mm, dtype=float)
    tcp = (origin[6] + np.sum(tool[:, None, None] * axes[6], axis=0)).T
    return Chain(
        world_T_frame=stacked.transpose(3, 0, 1, 2),  # a view, pose first
        x_prime=x_prime.transpose(2, 0, 1),
        y_beta=y_beta.transpose(2, 0, 1),
        tcp_mm=np.ascontiguousarray(tcp),
    )


def flange_pose(params: KinematicParams, q_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 4, 4) world_T_flange."""
    return chain(params, q_rad).world_T_frame[:, 6]


def tcp_position_mm(params: KinematicParams, q_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3) TCP position in the world frame, mm."""
    return chain(params, q_rad).tcp_mm


def geometric_jacobian(
    params: KinematicParams, q_rad: NDArray[np.float64], ch: Chain | None = None
) -> NDArray[np.float64]:
    """(n, 6, 6) geometric Jacobian of the TCP w.r.t. q (rad): rows vx, vy, vz (mm/rad), wx, wy, wz."""
    ch = ch if ch is not None else chain(params, q_rad)
    z = ch.world_T_frame[:, :6, :3, 2]  # (n, 6, 3) joint axes
    o = ch.world_T_frame[:, :6, :3, 3]
    lin = np.cross(z, ch.tcp_mm[:, None, :] - o)  # (n, 6, 3)
    return np.concatenate([lin.transpose(0, 2, 1), z.transpose(0, 2, 1)], axis=1)


def position_jacobian_mm(
    params: KinematicParams, q_rad: NDArray[np.float64], ch: Chain | None = None
) -> NDArray[np.float64]:
    """(n, 3, 6) derivative of the TCP position (mm) w.r.t. q (rad)."""
    return geometric_jacobian(params, q_rad, ch)[:, :3, :]


def identification_jacobian(
    params: KinematicParams, q_rad: NDArray[np.float64], ch: Chain | None = None
) -> NDArray[np.float64]:
    """(n, 3, 39) derivative of the TCP position w.r.t. the identification vector (PARAM_NAMES)."""
    ch = ch if ch is not None else chain(params, q_rad)
    n = ch.tcp_mm.shape[0]
    p = ch.tcp_mm[:, None, :]
    z_prev = ch.world_T_frame[:, :6, :3, 2]
    o_prev = ch.world_T_frame[:, :6, :3, 3]
    o_next = ch.world_T_frame[:, 1:, :3, 3]
    cols = np.empty((n, 6, 5, 3))
    cols[:, :, 0] = np.cross(z_prev, p - o_prev)  # theta offset
    cols[:, :, 1] = z_prev  # d
    cols[:, :, 2] = ch.x_prime  # a
    cols[:, :, 3] = np.cross(ch.x_prime, p - o_next)  # alpha
    cols[:, :, 4] = np.cross(ch.y_beta, p - o_next)  # beta
    jac = np.empty((n, 3, N_PARAMS))
    jac[:, :, :30] = cols.reshape(n, 30, 3).transpose(0, 2, 1)
    jac[:, :, 30:33] = np.eye(3)
    # small rotation e_k about the world axes (left-multiplied): d p / d e_k = e_k × p
    px, py, pz = ch.tcp_mm[:, 0], ch.tcp_mm[:, 1], ch.tcp_mm[:, 2]
    zero = np.zeros(n)
    jac[:, :, 33] = np.stack([zero, -pz, py], axis=1)
    jac[:, :, 34] = np.stack([pz, zero, -px], axis=1)
    jac[:, :, 35] = np.stack([-py, px, zero], axis=1)
    jac[:, :, 36:39] = ch.world_T_frame[:, 6, :3, :3]
    return jac


def gravity_torques_nm(
    params: KinematicParams,
    q_rad: NDArray[np.float64],
    link_mass_kg: NDArray[np.float64],
    link_com_mm: NDArray[np.float64],
    payload_kg: float | NDArray[np.float64] = 0.0,
    ch: Chain | None = None,
) -> NDArray[np.float64]:
    """(n, 6) static gravity torques (N m) about each joint axis z_{i-1}, in DH sign.

    The torque that gravity exerts on the links beyond the joint (the motor holds the opposite);
    this is the sign of ``tests/spec/kr210_fk_vectors.csv``.

    Gravity is −z of the robot base frame (frame 0). Link i's mass sits at ``link_com_mm[i]`` in
    frame i; the payload (scalar or per pose, kg) sits at the TCP.
    """
    ch = ch if ch is not None else chain(params, q_rad)
    n = ch.tcp_mm.shape[0]
    frames = ch.world_T_frame
    # the centres of mass in the world frame, mm: R_i · com_i + o_i
    rot = frames[:, 1:, :3, :3]
    com = np.asarray(link_com_mm, dtype=float)
    points = frames[:, 1:, :3, 3] + rot[..., 0] * com[:, 0, None] + rot[..., 1] * com[:, 1, None]
    points += rot[..., 2] * com[:, 2, None]
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    masses = np.concatenate([np.broadcast_to(link_mass_kg, (n, 6)), payload[:, None]], axis=1)
    points_m = np.concatenate([points, ch.tcp_mm[:, None, :]], axis=1) / 1000.0  # (n, 7, 3)
    # gravity f_b·u on body b, u the base frame's z axis (in the world frame: the measurement may
    # be in a tracker's frame); about joint j (axis z_j through o_j) the bodies beyond it (b ≥ j)
    # give z_j · Σ (p_b − o_j) × f_b u = z_j · ((Σ f_b p_b) − o_j Σ f_b) × u: suffix sums
    f = -GRAVITY_MPS2 * masses  # (n, 7) N
    f_sum = np.cumsum(f[:, ::-1], axis=1)[:, ::-1][:, :6]
    fp_sum = np.cumsum((f[:, :, None] * points_m)[:, ::-1], axis=1)[:, ::-1][:, :6]
    lever = fp_sum - frames[:, :6, :3, 3] / 1000.0 * f_sum[:, :, None]  # (n, 6, 3)
    up = frames[:, 0, :3, 2][:, None, :]  # (n, 1, 3)
    tau: NDArray[np.float64] = np.sum(frames[:, :6, :3, 2] * np.cross(lever, up), axis=2)
    return tau
