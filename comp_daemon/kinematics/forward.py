"""Batch forward kinematics, Jacobians and static gravity torques.

Every function takes ``q_rad`` of shape (n, 6) (joint angles in DH sign, see
:mod:`comp_daemon.kinematics.params`) and works on all n poses at once; a single pose is n = 1.
Frame names follow ``a_T_b`` (pose of b in a); ``world`` is the measurement frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import N_PARAMS, KinematicParams

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


def _as_batch(q_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    q = np.asarray(q_rad, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != 6:
        raise ValueError(f"joint angles must have shape (n, 6), got {q.shape}")
    return q


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


def chain(params: KinematicParams, q_rad: NDArray[np.float64]) -> Chain:
    """Forward kinematics of n poses with every intermediate frame kept (for Jacobians)."""
    q = _as_batch(q_rad)
    n = q.shape[0]
    theta = q + params.theta_offset_rad
    c, s = np.cos(theta), np.sin(theta)
    frames = np.empty((n, 7, 4, 4))
    frames[:, 0] = params.world_T_base
    x_prime = np.empty((n, 6, 3))
    y_beta = np.empty((n, 6, 3))
    ca, sa = np.cos(params.alpha_rad), np.sin(params.alpha_rad)
    cb, sb = np.cos(params.beta_rad), np.sin(params.beta_rad)
    for i in range(6):
        # M = Rx(alpha) Ry(beta); link rotation Rz(theta) M, translation Rz(theta)·(a, 0, d)
        m = np.array(
            [
                [cb[i], 0.0, sb[i]],
                [sa[i] * sb[i], ca[i], -sa[i] * cb[i]],
                [-ca[i] * sb[i], sa[i], ca[i] * cb[i]],
            ]
        )
        link = np.zeros((n, 4, 4))
        ci, si = c[:, i, None], s[:, i, None]
        link[:, 0, :3] = ci * m[0] - si * m[1]
        link[:, 1, :3] = si * m[0] + ci * m[1]
        link[:, 2, :3] = m[2]
        link[:, 0, 3] = params.a_mm[i] * c[:, i]
        link[:, 1, 3] = params.a_mm[i] * s[:, i]
        link[:, 2, 3] = params.d_mm[i]
        link[:, 3, 3] = 1.0
        prev_r = frames[:, i, :3, :3]
        x_prime[:, i] = prev_r[:, :, 0] * c[:, i, None] + prev_r[:, :, 1] * s[:, i, None]
        y_rot = -prev_r[:, :, 0] * s[:, i, None] + prev_r[:, :, 1] * c[:, i, None]
        y_beta[:, i] = ca[i] * y_rot + sa[i] * prev_r[:, :, 2]
        frames[:, i + 1] = frames[:, i] @ link
    flange = frames[:, 6]
    tcp = flange[:, :3, :3] @ params.tool_xyz_mm + flange[:, :3, 3]
    return Chain(world_T_frame=frames, x_prime=x_prime, y_beta=y_beta, tcp_mm=tcp)


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
    # positions in the robot base frame, so that "down" is −z of frame 0 even in a tracker frame
    world_T_base = ch.world_T_frame[:, 0]
    if n and np.array_equal(world_T_base, np.broadcast_to(world_T_base[0], world_T_base.shape)):
        base_T_world = np.linalg.inv(world_T_base[0])  # one base frame for every pose: invert it once
        frames = base_T_world @ ch.world_T_frame  # (n, 7, 4, 4)
        tcp = ch.tcp_mm @ base_T_world[:3, :3].T + base_T_world[:3, 3]
    else:
        each = np.linalg.inv(world_T_base)
        frames = each[:, None] @ ch.world_T_frame
        tcp = np.einsum("nij,nj->ni", each[:, :3, :3], ch.tcp_mm) + each[:, :3, 3]
    com = frames[:, 1:, :3, :3] @ link_com_mm[None, :, :, None]
    com = com[..., 0] + frames[:, 1:, :3, 3]  # (n, 6, 3) mm
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    masses = np.concatenate([np.broadcast_to(link_mass_kg, (n, 6)), payload[:, None]], axis=1)
    points_m = np.concatenate([com, tcp[:, None, :]], axis=1) / 1000.0  # (n, 7, 3)
    # gravity (0, 0, f_b) on body b; about joint j (axis z_j through o_j) the bodies beyond it
    # (b ≥ j) give z_j · Σ (p_b − o_j) × (0, 0, f_b) = z_jx·Σ f_b (p_by − o_jy) − z_jy·Σ f_b (p_bx − o_jx):
    # sums over b ≥ j, i.e. suffix sums of f_b and f_b·p_b
    f = -GRAVITY_MPS2 * masses  # (n, 7) N
    f_sum = np.cumsum(f[:, ::-1], axis=1)[:, ::-1][:, :6]
    fp_sum = np.cumsum((f[:, :, None] * points_m[:, :, :2])[:, ::-1], axis=1)[:, ::-1][:, :6]
    z = frames[:, :6, :3, 2]
    o_m = frames[:, :6, :3, 3] / 1000.0
    moment_x = fp_sum[..., 1] - o_m[..., 1] * f_sum
    moment_y = fp_sum[..., 0] - o_m[..., 0] * f_sum
    tau: NDArray[np.float64] = z[..., 0] * moment_x - z[..., 1] * moment_y
    return tau
