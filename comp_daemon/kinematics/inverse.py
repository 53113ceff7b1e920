"""Numerical inverse kinematics, batch over n targets.

Damped least squares (Levenberg–Marquardt style, the damping adapted per target) on the TCP position,
and on the TCP orientation when one is given. Each target starts from its own seed — a nearby
solution such as the current joint state or the previous target's answer — so the solver stays on
the seed's branch (elbow up/down, wrist flip). Joint limits are respected by clamping every step into
the limits; a target that cannot be reached within tolerance comes back with ``ok = False``, and
:func:`require_reachable` turns that into an :class:`UnreachableTargetError` naming the targets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import chain, geometric_jacobian
from comp_daemon.kinematics.params import KinematicParams

__all__ = [
    "IKResult",
    "UnreachableTargetError",
    "orientation_error_rad",
    "require_reachable",
    "solve_ik",
    "solve_ik_axes",
]


class UnreachableTargetError(ValueError):
    """Targets that inverse kinematics could not reach within tolerance and joint limits."""

    def __init__(
        self, indices: NDArray[np.intp], position_error_mm: NDArray[np.float64], what: str = "target"
    ):
        self.indices = np.asarray(indices)
        self.position_error_mm = np.asarray(position_error_mm)
        shown = ", ".join(
            f"{what} {int(i) + 1} (left {e:.3f} mm)"
            for i, e in zip(self.indices[:5], self.position_error_mm[:5], strict=False)
        )
        more = f" and {len(self.indices) - 5} more" if len(self.indices) > 5 else ""
        super().__init__(f"unreachable within joint limits: {shown}{more}")


@dataclass(frozen=True, slots=True)
class IKResult:
    q_rad: NDArray[np.float64]  # (n, 6)
    ok: NDArray[np.bool_]  # (n,)
    position_error_mm: NDArray[np.float64]  # (n,)
    orientation_error_rad: NDArray[np.float64]  # (n,) zeros when no orientation was asked for
    iterations: int


def orientation_error_rad(
    world_R_tcp: NDArray[np.float64], target_R: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(n, 3) rotation vector (world frame) taking the current orientation to the target."""
    delta = target_R @ np.swapaxes(world_R_tcp, 1, 2)
    cos_angle = np.clip((np.trace(delta, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_angle)
    axis = np.stack(
        [delta[:, 2, 1] - delta[:, 1, 2], delta[:, 0, 2] - delta[:, 2, 0], delta[:, 1, 0] - delta[:, 0, 1]],
        axis=1,
    )
    sin_angle = np.sin(angle)
    scale = np.where(sin_angle > 1e-9, angle / (2.0 * np.where(sin_angle > 1e-9, sin_angle, 1.0)), 0.5)
    return axis * scale[:, None]


def solve_ik(
    params: KinematicParams,
    limits_q_rad: NDArray[np.float64],
    target_p_mm: NDArray[np.float64],
    target_R: NDArray[np.float64] | None,
    q_seed_rad: NDArray[np.float64],
    *,
    tol_mm: float = 1e-6,
    tol_rad: float = 1e-9,
    max_iter: int = 200,
    max_step_rad: float = 0.2,
) -> IKResult:
    """Joint angles q (rad, DH sign) that put the TCP at ``target_p_mm`` (and ``target_R``, if given).

    ``limits_q_rad`` is (6, 2) [low, high] in q (mind the joint's sign when converting axis limits).
    Orientation errors are weighted by a 1000 mm lever so that both parts of the residual are in mm.
    """
    target_p = np.atleast_2d(np.asarray(target_p_mm, dtype=float))
    n = target_p.shape[0]
    q = np.array(np.broadcast_to(np.asarray(q_seed_rad, dtype=float), (n, 6)))
    lo, hi = limits_q_rad[:, 0], limits_q_rad[:, 1]
    q = np.clip(q, lo, hi)
    use_rot = target_R is not None
    lever_mm = 1000.0
    lam = np.full(n, 1e-2)
    active = np.ones(n, dtype=bool)
    iterations = 0

    def residual(qq: NDArray[np.float64], idx: NDArray[np.intp]) -> tuple[NDArray[np.float64], object]:
        ch = chain(params, qq)
        e_p = target_p[idx] - ch.tcp_mm
        if use_rot:
            assert target_R is not None
            r_tcp = ch.world_T_frame[:, 6, :3, :3]
            e_r = orientation_error_rad(r_tcp, target_R[idx]) * lever_mm
            return np.concatenate([e_p, e_r], axis=1), ch
        return e_p, ch

    for iterations in range(1, max_iter + 1):  # noqa: B007
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        qa = q[idx]
        err, ch = residual(qa, idx)
        jac = geometric_jacobian(params, qa, ch)  # type: ignore[arg-type]
        if use_rot:
            jac = np.concatenate([jac[:, :3], jac[:, 3:] * lever_mm], axis=1)
        else:
            jac = jac[:, :3]
        cost = np.einsum("ni,ni->n", err, err)
        # isotropic damping (JᵀJ + λ·s·I), s the mean curvature: for a redundant (position-only)
        # target the step is the damped minimum-norm one, so the answer stays near the seed
        jtj = np.swapaxes(jac, 1, 2) @ jac
        jte = np.einsum("nij,ni->nj", jac, err)
        scale = np.einsum("nii->n", jtj) / 6.0 + 1.0
        a = jtj + (lam[idx] * scale)[:, None, None] * np.eye(6)
        step = np.linalg.solve(a, jte[..., None])[..., 0]
        norm = np.abs(step).max(axis=1)
        step *= np.minimum(1.0, max_step_rad / np.maximum(norm, 1e-300))[:, None]
        q_new = np.clip(qa + step, lo, hi)
        err_new, _ = residual(q_new, idx)
        cost_new = np.einsum("ni,ni->n", err_new, err_new)
        better = cost_new < cost
        q[idx[better]] = q_new[better]
        lam[idx] = np.where(better, np.maximum(lam[idx] / 3.0, 1e-9), np.minimum(lam[idx] * 4.0, 1e6))
        e_final = np.where(better[:, None], err_new, err)
        pos_ok = np.linalg.norm(e_final[:, :3], axis=1) < tol_mm
        rot_ok = np.linalg.norm(e_final[:, 3:], axis=1) / lever_mm < tol_rad if use_rot else True
        moved = np.abs(q_new - qa).max(axis=1) > 1e-15
        stalled = (~better & (lam[idx] >= 1e6)) | (better & ~moved)
        active[idx[(pos_ok & rot_ok) | stalled]] = False

    err, ch = residual(q, np.arange(n))
    pos_err = np.linalg.norm(err[:, :3], axis=1)
    rot_err = np.linalg.norm(err[:, 3:], axis=1) / lever_mm if use_rot else np.zeros(n)
    ok = (pos_err < max(tol_mm, 1e-4) * 10) & (rot_err < max(tol_rad, 1e-7) * 10)
    return IKResult(
        q_rad=q, ok=ok, position_error_mm=pos_err, orientation_error_rad=rot_err, iterations=iterations
    )


def require_reachable(result: IKResult, what: str = "target") -> NDArray[np.float64]:
    """The solution's q (rad), or :class:`UnreachableTargetError` naming every failed target."""
    bad = np.flatnonzero(~result.ok)
    if bad.size:
        raise UnreachableTargetError(bad, result.position_error_mm[bad], what)
    return result.q_rad


def solve_ik_axes(
    params: KinematicParams,
    sign: NDArray[np.float64],
    axis_limits_deg: NDArray[np.float64],
    target_p_mm: NDArray[np.float64],
    target_R: NDArray[np.float64] | None,
    seed_a_deg: NDArray[np.float64],
) -> tuple[NDArray[np.float64], IKResult]:
    """:func:`solve_ik` in the controller's axis values: seeds and answer in deg (n, 6)."""
    limits_q = np.sort(np.deg2rad(axis_limits_deg) * sign[:, None], axis=1)
    result = solve_ik(params, limits_q, target_p_mm, target_R, np.deg2rad(seed_a_deg) * sign)
    return np.rad2deg(result.q_rad) * sign, result
