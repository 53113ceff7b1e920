"""The POE chain with a full twist error per joint and a tool offset error (the ``poe`` kind's form).

Seed 002 keeps 12 errors (``dl1..dl6`` along the nominal segments, ``dtheta1..dtheta6``) and drops
the axis-direction errors Δω (spec A.2: "Δω is dropped"); the tool is nominal. A robot whose axes
are tilted or shifted off their nominal lines, or whose tool is not where the description says,
keeps part of its error under that model. Here every joint carries a whole constant rigid error
``E_i`` in front of its exponential, and the tool offset carries its own::

    base_T_flange(A) = E_1·exp([ξ_1]A_1) · E_2·exp([ξ_2]A_2) ··· E_6·exp([ξ_6]A_6) · base_T_flange0
    p_tcp = base_T_flange(A) · [tool_xyz_mm + (tool_x, tool_y, tool_z), 1]

``E_i`` is written in joint i's own nominal frame at the zero pose (origin the axis point ``q_i``,
axes ``u_i, n_i, ω_i`` with ``ω_i`` the joint axis): ``E_i = F_i·D_i·F_i⁻¹``, ``D_i`` the rotation
vector ``(dwu_i, dwn_i, dtheta_i)`` (rad) and the translation ``(dpu_i, dpn_i, dlax_i)`` (mm). So
``dtheta_i`` is the zero offset (a turn about the axis), ``dwu_i, dwn_i`` tilt the axis direction
(the Δω of spec A.2), ``dpu_i, dpn_i`` shift the axis line off its nominal point and ``dlax_i``
slides everything beyond along it (the Δl of the segment that ends at ``q_i``, where the segment
lies along the axis). With all 39 errors zero the chain is the nominal POE chain
(:mod:`comp_daemon.kinematics.poe`).

The 39 errors and a fitted base frame are far from independent (a base frame absorbs ``E_1`` whole;
a slide along an axis at the zero pose is a shift of the next point; …): the identifiability
analysis of seed 003 removes the dependent ones by name in the order of :data:`TWIST_PRIORITY` (the
base frame and tool first, then per joint the zero offset, the axis tilts, the axis shifts, the
slide), each with the kept parameters it depends on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.estimation.identifiability import analyze_identifiability
from comp_daemon.estimation.registration import rigid_registration
from comp_daemon.kinematics.poe import PoeModel, poe_chain
from comp_daemon.kinematics.so3 import left_jacobian, rotvec_to_matrix, skew
from comp_daemon.models.poe.calibration import (
    BASE_NAMES,
    PositionFit,
    fit_least_squares_subset,
    measured_positions,
    null_directions,
    rms_distance_mm,
    start_frame,
)

_log = get_logger(__name__)

__all__ = [
    "N_TWIST_PARAMS",
    "TOOL_NAMES",
    "TWIST_KINDS",
    "TWIST_PARAM_NAMES",
    "TWIST_PRIORITY",
    "PoeTwistFit",
    "fit_poe_twists",
    "joint_frames",
    "twist_chain",
    "twist_world_jacobian",
]

TWIST_KINDS: tuple[str, ...] = ("dtheta", "dwu", "dwn", "dpu", "dpn", "dlax")  # rad ×3, mm ×3
TOOL_NAMES: tuple[str, ...] = ("tool_x", "tool_y", "tool_z")
TWIST_PARAM_NAMES: tuple[str, ...] = (
    *(f"{k}{j}" for j in range(1, 7) for k in TWIST_KINDS),
    *TOOL_NAMES,
)
N_TWIST_PARAMS = len(TWIST_PARAM_NAMES)  # 39
TWIST_PRIORITY: tuple[str, ...] = (
    *TOOL_NAMES,
    *(f"{k}{j}" for k in TWIST_KINDS for j in range(1, 7)),
)


def joint_frames(model: PoeModel) -> NDArray[np.float64]:
    """(6, 3, 3) each joint's nominal frame at the zero pose: columns ``u_i, n_i, ω_i``."""
    out = np.empty((6, 3, 3))
    for i, w in enumerate(model.omega):
        helper = np.eye(3)[int(np.argmin(np.abs(w)))]
        u = np.cross(helper, w)
        u /= np.linalg.norm(u)
        out[i] = np.column_stack([u, np.cross(w, u), w])
    return out


def twist_chain(
    model: PoeModel, a_deg: NDArray[np.float64], e: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """TCP (n, 3) in the robot base frame and its derivative (n, 3, 39) w.r.t. the errors ``e``
    (:data:`TWIST_PARAM_NAMES` order) at ``e``."""
    a = np.atleast_2d(np.asarray(a_deg, dtype=float))
    err = np.asarray(e, dtype=float)
    if err.shape != (N_TWIST_PARAMS,):
        raise ValueError(f"twist errors must have shape ({N_TWIST_PARAMS},), got {err.shape}")
    n = a.shape[0]
    theta = np.deg2rad(a)
    frames = joint_frames(model)
    per_joint = err[:36].reshape(6, 6)  # dtheta, dwu, dwn, dpu, dpn, dlax
    w_local = per_joint[:, [1, 2, 0]]  # rotation vector (u, n, ω)
    v_local = per_joint[:, [3, 4, 5]]
    rot = np.empty((n, 3, 3))
    rot[:] = np.eye(3)
    trans = np.zeros((n, 3))
    before_rot = np.empty((6, n, 3, 3))
    before_trans = np.empty((6, n, 3))
    for i in range(6):
        b, q = frames[i], model.point_mm[i]
        m = b @ rotvec_to_matrix(w_local[i]) @ b.T
        c = q + b @ v_local[i] - m @ q
        before_rot[i], before_trans[i] = rot, trans
        trans = rot @ c + trans
        rot = rot @ m
        k = skew(model.omega[i])
        s, co = np.sin(theta[:, i]), np.cos(theta[:, i])
        r_i = np.eye(3) + s[:, None, None] * k + (1.0 - co)[:, None, None] * (k @ k)
        trans = (rot @ (q - (r_i @ q))[..., None])[..., 0] + trans
        rot = rot @ r_i
    flange_r = rot @ model.base_R_flange0
    flange_t = rot @ model.flange0_mm + trans
    tcp = flange_r @ (model.tool_xyz_mm + err[36:39]) + flange_t
    jac = np.empty((n, 3, N_TWIST_PARAMS))
    for i in range(6):
        b = frames[i]
        r_p, t_p = before_rot[i], before_trans[i]
        after_e = np.einsum("nji,nj->ni", r_p, tcp - t_p)  # the TCP in the frame right after E_i
        local = (after_e - model.point_mm[i]) @ b - v_local[i]  # = R(w)·B_iᵀ(y − q_i)
        rb = r_p @ b  # (n, 3, 3)
        d_w = -rb @ skew(local) @ left_jacobian(w_local[i])  # columns (u, n, ω)
        cols = 6 * i
        jac[:, :, cols] = d_w[:, :, 2]  # dtheta
        jac[:, :, cols + 1] = d_w[:, :, 0]  # dwu
        jac[:, :, cols + 2] = d_w[:, :, 1]  # dwn
        jac[:, :, cols + 3 : cols + 6] = rb  # dpu, dpn, dlax
    jac[:, :, 36:39] = flange_r
    return tcp, jac


def twist_world_jacobian(
    model: PoeModel, a_deg: NDArray[np.float64], theta: NDArray[np.float64], start_T_base: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World TCP (n, 3) and its Jacobian (n, 3, 39 + 6) w.r.t. ``theta`` = (twist errors, base
    parameters: increments of ``start_T_base``, translation mm and rotation vector rad on the left)."""
    tcp, jac_e = twist_chain(model, a_deg, theta[:N_TWIST_PARAMS])
    b = theta[N_TWIST_PARAMS:]
    world = start_frame(start_T_base, b)
    p = tcp @ world[:3, :3].T + world[:3, 3]
    jac = np.empty((p.shape[0], 3, N_TWIST_PARAMS + 6))
    jac[:, :, :N_TWIST_PARAMS] = world[:3, :3] @ jac_e
    jac[:, :, N_TWIST_PARAMS : N_TWIST_PARAMS + 3] = np.eye(3)
    jac[:, :, N_TWIST_PARAMS + 3 :] = -skew(p - b[:3]) @ left_jacobian(b[3:])
    return p, jac


@dataclass(frozen=True, slots=True)
class PoeTwistFit(PositionFit):
    """A calibration of the twist errors and the base frame (``names``: TWIST_PARAM_NAMES +
    BASE_NAMES; removed parameters zero)."""

    world_T_base: NDArray[np.float64]

    @property
    def errors(self) -> NDArray[np.float64]:
        """The 39 twist and tool errors."""
        return self.theta[:N_TWIST_PARAMS]


def fit_poe_twists(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    p_meas_mm: NDArray[np.float64],
    start_T_base: NDArray[np.float64] | None = None,
    *,
    rtol: float = 1e-7,
) -> PoeTwistFit:
    """The twist errors, the tool offset error and the base frame from measured TCPs (n, 3) at
    ``a_deg`` (n, 6); the frame starts at ``start_T_base`` (default: the rigid registration of the
    nominal TCPs onto the measured ones). Dependent parameters are removed by name
    (:data:`TWIST_PRIORITY`, frame first) and stay zero; improved LM on the rest."""
    a, p_meas = measured_positions(a_deg, p_meas_mm)
    start = rigid_registration(poe_chain(model, a).tcp_mm, p_meas) if start_T_base is None else start_T_base
    names = TWIST_PARAM_NAMES + BASE_NAMES
    theta0 = np.zeros(len(names))

    def fn(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p, jac = twist_world_jacobian(model, a, theta, start)
        return (p - p_meas).reshape(-1), jac.reshape(-1, len(names))

    r0, jac0 = fn(theta0)
    priority = [*BASE_NAMES, *TWIST_PRIORITY]
    report = analyze_identifiability(jac0, list(names), priority=priority, rtol=rtol, rank_rtol=rtol)
    keep = report.identifiable_index
    theta, std, _, its, reason, r = fit_least_squares_subset(fn, theta0, keep, inverse_variance=False)
    rms0, rms1 = rms_distance_mm(r0), rms_distance_mm(r)
    _log.info(
        "poe twist fit", points=a.shape[0], kept=report.n_identifiable, rms_before_mm=rms0, rms_after_mm=rms1
    )
    return PoeTwistFit(
        names=names,
        theta=theta,
        std=std,
        world_T_base=start_frame(start, theta[N_TWIST_PARAMS:]),
        report=report,
        null_space=null_directions(report, jac0),
        rms_before_mm=rms0,
        rms_after_mm=rms1,
        iterations=its,
        reason=reason,
    )
