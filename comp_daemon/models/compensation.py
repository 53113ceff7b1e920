"""Compensation: commanded axis values whose *predicted* actual TCP is the wanted one.

Targets are given in the robot base frame (mm; optional orientation as rotation matrices) and
mapped into the model's measurement frame by its ``registration``. Two methods:

:func:`compensate` — model + inverse kinematics, iterated. Start from the inverse kinematics of the
target on the model's kinematic parameters (``ik_params``); then repeat: predict the actual TCP of
the current command with the model, move the IK target by the remaining error
(``target_ik ← target_ik + (wanted − predicted)``) and solve the IK again from the current command,
until the predicted TCP is within ``tol_mm`` of the wanted one. The orientation, when given, is held
on the IK parameters (the tracker data are positions only). This is a fixed-point iteration that
contracts with the ratio of the model's error slope to the Jacobian's (per mille for a robot), so a
handful of iterations reach rounding level.

:func:`joint_mapping` — the joint mapping of seed 000 (§2.2): the estimated Cartesian error ``ΔP``
(predicted actual − wanted, mm) of a command is mapped to corrections of joints 1–3 by least
squares on the position Jacobian of those joints, ``Δθ = (J₁₂₃ᵀJ₁₂₃)⁻¹J₁₂₃ᵀ ΔP``, and the modified
joint targets are ``θ − Δθ`` (the feed-forward of the closed loop, whose gratings sit on joints 1–3).
:func:`feed_forward` applies it to commands whose nominal TCP is the wanted one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import chain, position_jacobian_mm
from comp_daemon.kinematics.inverse import require_reachable, solve_ik
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad, q_rad_to_axes_deg
from comp_daemon.models.base import ErrorModel, as_axes
from comp_daemon.models.registration import transform_points
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "CompensationResult",
    "FeedForward",
    "axis_limits_q_rad",
    "compensate",
    "feed_forward",
    "joint_mapping",
    "nominal_targets",
]

MAPPED_JOINTS = (1, 2, 3)


def axis_limits_q_rad(robot: RobotDescription) -> NDArray[np.float64]:
    """(6, 2) joint limits in q (rad, DH sign): the axis limits with each joint's sign applied."""
    return np.sort(axes_deg_to_q_rad(robot.axis_limits_deg, robot.sign[:, None]), axis=1)


@dataclass(frozen=True, slots=True)
class CompensationResult:
    a_deg: NDArray[np.float64]  # (n, 6) compensated commands
    a_uncompensated_deg: NDArray[np.float64]  # (n, 6) IK of the wanted TCP on the IK parameters alone
    wanted_mm: NDArray[np.float64]  # (n, 3) in the measurement frame
    predicted_mm: NDArray[np.float64]  # (n, 3) the model's prediction at a_deg
    residual_mm: NDArray[np.float64]  # (n,) |predicted − wanted|
    iterations: int
    converged: bool


def nominal_targets(
    model: ErrorModel, a_deg: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Wanted TCP positions (n, 3) and orientations (n, 3, 3), robot base frame, of nominal commands."""
    params = KinematicParams.from_robot(model.robot)
    ch = chain(params, axes_deg_to_q_rad(as_axes(a_deg), params.sign))
    return ch.tcp_mm, ch.world_T_frame[:, 6, :3, :3]


def compensate(
    model: ErrorModel,
    target_p_base_mm: NDArray[np.float64],
    target_R_base: NDArray[np.float64] | None = None,
    *,
    a_seed_deg: NDArray[np.float64] | None = None,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float | None = None,
    temp_c: NDArray[np.float64] | None = None,
    tol_mm: float = 1e-8,
    max_iter: int = 30,
) -> CompensationResult:
    """Commands (deg) whose predicted TCP equals the wanted ``target_p_base_mm`` (n, 3), base frame.

    ``a_seed_deg`` (n, 6) or (6,): where the inverse kinematics starts (the nominal program's axis
    values, or a neighbouring pose); default the middle of every axis range.
    Raises :class:`comp_daemon.kinematics.inverse.UnreachableTargetError` naming unreachable targets.
    """
    target = np.atleast_2d(np.asarray(target_p_base_mm, dtype=float))
    if target.ndim != 2 or target.shape[1] != 3:
        raise ValueError(f"target positions must have shape (n, 3), got {np.shape(target_p_base_mm)}")
    n = target.shape[0]
    reg = model.registration
    wanted = transform_points(reg, target)
    rot = None
    if target_R_base is not None:
        rot = np.asarray(target_R_base, dtype=float).reshape(n, 3, 3)
        rot = reg[:3, :3] @ rot
    params: KinematicParams = model.ik_params()
    limits = axis_limits_q_rad(model.robot)
    if a_seed_deg is None:
        a_seed = np.broadcast_to(model.robot.axis_limits_deg.mean(axis=1), (n, 6))
    else:
        a_seed = np.broadcast_to(np.asarray(a_seed_deg, dtype=float), (n, 6))
    q_seed = axes_deg_to_q_rad(a_seed, params.sign)
    ik_tol = min(tol_mm, 1e-9) / 10.0

    def solve(p_ik: NDArray[np.float64], seed: NDArray[np.float64], what: str) -> NDArray[np.float64]:
        res = solve_ik(params, limits, p_ik, rot, seed, tol_mm=ik_tol, tol_rad=1e-12)
        return require_reachable(res, what)

    q = solve(wanted, q_seed, "target")
    a_first = q_rad_to_axes_deg(q, params.sign)
    p_ik = wanted.copy()
    converged = False
    iterations = 0
    predicted = model.predict_tcp_mm(a_first, dir, payload_kg, temp_c)
    for iterations in range(1, max_iter + 1):  # noqa: B007
        err = wanted - predicted
        if float(np.max(np.linalg.norm(err, axis=1), initial=0.0)) <= tol_mm:
            converged = True
            break
        p_ik = p_ik + err
        q = solve(p_ik, q, "compensated target")
        predicted = model.predict_tcp_mm(q_rad_to_axes_deg(q, params.sign), dir, payload_kg, temp_c)
    a_final = q_rad_to_axes_deg(q, params.sign)
    residual = np.linalg.norm(predicted - wanted, axis=1)
    return CompensationResult(
        a_deg=a_final,
        a_uncompensated_deg=a_first,
        wanted_mm=wanted,
        predicted_mm=predicted,
        residual_mm=residual,
        iterations=iterations,
        converged=converged or bool(np.all(residual <= tol_mm)),
    )


def joint_mapping(
    params: KinematicParams, a_deg: NDArray[np.float64], error_mm: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(n, 6) axis corrections (deg, controller convention) of seed 000's joint mapping.

    ``error_mm`` (n, 3) is the estimated TCP error (actual − wanted) at the commands ``a_deg``; the
    corrections are zero on joints 4–6 and ``−Δθ`` on joints 1–3 with ``Δθ`` the least-squares
    solution of ``J₁₂₃·Δθ = ΔP`` (position Jacobian of joints 1–3 at ``a_deg``). Near a singularity
    of ``J₁₂₃`` (the TCP close to axis 1, a stretched arm) the corrections grow without bound; callers
    that move a robot limit them.
    """
    a = as_axes(a_deg)
    err = np.asarray(error_mm, dtype=float).reshape(a.shape[0], 3)
    q = axes_deg_to_q_rad(a, params.sign)
    jac = position_jacobian_mm(params, q)[:, :, : len(MAPPED_JOINTS)]  # (n, 3, 3)
    jtj = np.swapaxes(jac, 1, 2) @ jac
    jte = np.einsum("nij,ni->nj", jac, err)
    dtheta = np.linalg.solve(jtj, jte[..., None])[..., 0]  # (n, 3) rad, DH sign
    out = np.zeros_like(a)
    out[:, : len(MAPPED_JOINTS)] = -q_rad_to_axes_deg(dtheta, params.sign[: len(MAPPED_JOINTS)])
    return out


@dataclass(frozen=True, slots=True)
class FeedForward:
    a_deg: NDArray[np.float64]  # (n, 6) modified joint targets (joints 1–3 corrected)
    correction_deg: NDArray[np.float64]  # (n, 6) added to the nominal commands
    estimated_error_mm: NDArray[np.float64]  # (n, 3) the model's error at the nominal commands


def feed_forward(
    model: ErrorModel,
    a_nominal_deg: NDArray[np.float64],
    *,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float | None = None,
    temp_c: NDArray[np.float64] | None = None,
) -> FeedForward:
    """Seed 000 step (4): estimated error of nominal commands, mapped onto joints 1–3."""
    a = as_axes(a_nominal_deg)
    wanted_base, _ = nominal_targets(model, a)
    wanted = transform_points(model.registration, wanted_base)
    error = model.predict_tcp_mm(a, dir, payload_kg, temp_c) - wanted
    corr = joint_mapping(model.ik_params(), a, error)
    return FeedForward(a_deg=a + corr, correction_deg=corr, estimated_error_mm=error)
