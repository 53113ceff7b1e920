"""Seed 004's point-constraint identification: laser lines through one point (a PSD).

Identification, as the paper formulates it (point constraint, §3, after Liu et al. [13–15]): a
laser on the flange casts a line from ``o`` along ``u``; the robot is servoed in several poses
until the beam hits the centre of a position sensitive detector (PSD), so all lines pass through
one unknown point ``P``. Per pose the constraint residual is the part of ``P − o`` normal to the
beam, ``r = (I − uuᵀ)(P − o)`` (mm, rank 2). The unknowns are the ``Δθ``, the ``C`` and ``P``;
they are solved by the improved Levenberg–Marquardt method of seed 000
(:func:`comp_daemon.estimation.lm.improved_lm`) with the exact Jacobian::

    ∂o/∂θ_i = z_{i−1} × (o − p_{i−1}),   ∂u/∂θ_i = z_{i−1} × u
    ∂r/∂θ_i = −(I − uuᵀ)·∂o/∂θ_i − (∂u·uᵀ + u·∂uᵀ)(P − o),   ∂r/∂C_i = τ_i·∂r/∂θ_i,   ∂r/∂P = I − uuᵀ

Which unknowns the constraint can determine is decided by the identifiability analysis of
:mod:`comp_daemon.estimation.identifiability` on the Jacobian of a consistent set of lines: ``Δθ1`` is
not (a turn of the whole set-up, ``P`` included, about the vertical base axis), which is why the
paper's simulated zero offset of joint 1 is 0. Seed 004 calibrates on 7 poses at a time, repeats
this 30 times over its 210 calibration poses, and averages the 30 results.


Evaluation (the paper's): with the identified parameters, each validation pose's model laser line
is intersected with the PSD plane; its distance from the PSD centre is the *distance error*
(:func:`psd_distance_errors_mm`).

The model identified is :class:`comp_daemon.models.compliance.ComplianceModel`; this module and
:mod:`benchmarks.seed004_compliance` reproduce the paper's experiment with it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.identifiability import analyze_identifiability
from comp_daemon.estimation.lm import improved_lm
from comp_daemon.kinematics.forward import gravity_torques_nm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, joint_param_index
from comp_daemon.models.base import as_axes, finite_array
from comp_daemon.models.compliance import (
    ALL_JOINTS,
    COMPLIANCE_JOINTS,
    N_JOINTS,
    ComplianceFit,
    ComplianceModel,
    joint_numbers,
    standard_errors,
)
from comp_daemon.models.effects import EffectParams, MassModel, twin_state
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "LaserMount",
    "PointConstraintFit",
    "calibrate_point_constraint",
    "laser_lines",
    "line_distance_errors_mm",
    "point_constraint_jacobian",
    "psd_distance_errors_mm",
]


@dataclass(frozen=True, slots=True)
class LaserMount:
    """The laser on the flange: beam origin (mm) and unit direction, both in the flange frame."""

    origin_mm: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 40.0, 60.0]))
    direction: NDArray[np.float64] = field(
        default_factory=lambda: np.array([np.sin(np.deg2rad(20.0)), 0.0, np.cos(np.deg2rad(20.0))])
    )

    def __post_init__(self) -> None:
        o = finite_array(self.origin_mm, (3,), "LaserMount.origin_mm")
        u = finite_array(self.direction, (3,), "LaserMount.direction")
        norm = float(np.linalg.norm(u))
        if norm < 1e-9:
            raise ValueError("LaserMount.direction must not be zero")
        object.__setattr__(self, "origin_mm", o)
        object.__setattr__(self, "direction", u / norm)


@dataclass(frozen=True, slots=True)
class _Lines:
    o: NDArray[np.float64]  # (n, 3) beam origins
    u: NDArray[np.float64]  # (n, 3) unit directions
    z: NDArray[np.float64]  # (n, 6, 3) joint axes z_{i-1}
    p: NDArray[np.float64]  # (n, 6, 3) points on them
    tau: NDArray[np.float64]  # (n, 6) gravity torques at the commanded configuration


def _lines(
    mass: MassModel,
    params: KinematicParams,
    compliance: NDArray[np.float64],
    a: NDArray[np.float64],
    mount: LaserMount,
    payload: NDArray[np.float64] | float,
) -> _Lines:
    st = twin_state(mass, params, EffectParams(compliance_rad_per_nm=compliance), a, None, payload, None)
    frames = st.chain.world_T_frame
    r_f, p_f = frames[:, 6, :3, :3], frames[:, 6, :3, 3]
    o = r_f @ mount.origin_mm + p_f
    u = r_f @ mount.direction
    tau = st.tau_nm
    if not np.any(compliance != 0.0):
        q_cmd = params.sign * np.deg2rad(a)
        tau = gravity_torques_nm(params, q_cmd, mass.link_mass_kg, mass.link_com_mm, payload)
    return _Lines(o=o, u=u, z=frames[:, :6, :3, 2], p=frames[:, :6, :3, 3], tau=tau)


def laser_lines(
    robot_or_mass: RobotDescription | MassModel,
    params: KinematicParams,
    compliance_rad_per_nm: NDArray[np.float64] | Sequence[float],
    a_deg: NDArray[np.float64],
    mount: LaserMount,
    payload_kg: NDArray[np.float64] | float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Beam origins (n, 3, mm) and unit directions (n, 3) in the world frame of ``params``."""
    mass = robot_or_mass if isinstance(robot_or_mass, MassModel) else MassModel.from_robot(robot_or_mass)
    comp = finite_array(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
    ln = _lines(mass, params, comp, as_axes(a_deg), mount, payload_kg)
    return ln.o, ln.u


def _point_residual(ln: _Lines, point: NDArray[np.float64]) -> NDArray[np.float64]:
    w = point - ln.o
    return w - ln.u * np.einsum("ni,ni->n", ln.u, w)[:, None]


def _point_jacobian(
    ln: _Lines, point: NDArray[np.float64], joints: Sequence[int], comp_joints: Sequence[int]
) -> NDArray[np.float64]:
    """(n, 3, len(joints) + len(comp_joints) + 3): d r / d [Δθ_j, C_j, P]."""
    n = ln.o.shape[0]
    u = ln.u
    w = point - ln.o
    proj = np.eye(3) - u[:, :, None] * u[:, None, :]  # (n, 3, 3)
    uw = np.einsum("ni,ni->n", u, w)

    def d_theta(i: int) -> NDArray[np.float64]:
        z = ln.z[:, i]
        do = np.cross(z, ln.o - ln.p[:, i])
        du = np.cross(z, u)
        return (
            -np.einsum("nij,nj->ni", proj, do) - du * uw[:, None] - u * np.einsum("ni,ni->n", du, w)[:, None]
        )

    cols = [d_theta(j - 1) for j in joints]
    cols += [d_theta(j - 1) * ln.tau[:, j - 1, None] for j in comp_joints]
    jac = np.empty((n, 3, len(cols) + 3))
    for k, col in enumerate(cols):
        jac[:, :, k] = col
    jac[:, :, len(cols) :] = proj
    return jac


def point_constraint_jacobian(
    robot_or_mass: RobotDescription | MassModel,
    params: KinematicParams,
    compliance_rad_per_nm: NDArray[np.float64] | Sequence[float],
    a_deg: NDArray[np.float64],
    mount: LaserMount,
    point_mm: NDArray[np.float64],
    *,
    offset_joints: Sequence[int] = ALL_JOINTS,
    compliance_joints: Sequence[int] = COMPLIANCE_JOINTS,
    payload_kg: NDArray[np.float64] | float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Residual ``(I − uuᵀ)(P − o)`` (n, 3) and its Jacobian (n, 3, p) w.r.t. [Δθ, C, P] (module doc).

    Columns: ``theta{j}`` for ``offset_joints`` (mm/rad), ``C{j}`` for ``compliance_joints``
    (mm per rad/(N m)), then ``P_x, P_y, P_z`` (1).
    """
    mass = robot_or_mass if isinstance(robot_or_mass, MassModel) else MassModel.from_robot(robot_or_mass)
    comp = finite_array(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
    point = finite_array(point_mm, (3,), "point_mm")
    ln = _lines(mass, params, comp, as_axes(a_deg), mount, payload_kg)
    jac = _point_jacobian(ln, point, offset_joints, compliance_joints)
    return _point_residual(ln, point), jac


def _consistent_poses(
    mass: MassModel,
    params: KinematicParams,
    a: NDArray[np.float64],
    mount: LaserMount,
    point: NDArray[np.float64],
    payload: NDArray[np.float64] | float,
    iterations: int = 20,
) -> NDArray[np.float64]:
    """Axis values (deg) near ``a`` whose lines (of ``params``) pass through ``point``.

    Minimum-norm Gauss–Newton steps on the constraint residual, all poses at once.
    """
    a = a.copy()
    zero = np.zeros(N_JOINTS)
    for _ in range(iterations):
        ln = _lines(mass, params, zero, a, mount, payload)
        r = _point_residual(ln, point)
        if float(np.abs(r).max()) < 1e-12:
            break
        jac = _point_jacobian(ln, point, ALL_JOINTS, ())[:, :, :N_JOINTS]
        step = -np.einsum("nij,nj->ni", np.linalg.pinv(jac, rcond=1e-10), r)
        a = a + params.sign * np.rad2deg(step)
    return a


def _intersection_point(o: NDArray[np.float64], u: NDArray[np.float64]) -> NDArray[np.float64]:
    """The point nearest to all lines in the least-squares sense."""
    proj = np.eye(3) - u[:, :, None] * u[:, None, :]
    return np.linalg.solve(proj.sum(axis=0), np.einsum("nij,nj->i", proj, o))


@dataclass(frozen=True, slots=True)
class PointConstraintFit:
    """A point-constraint calibration: the model, the estimated constraint point and the details."""

    fit: ComplianceFit
    point_mm: NDArray[np.float64]

    @property
    def model(self) -> ComplianceModel:
        return self.fit.model


def calibrate_point_constraint(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    mount: LaserMount,
    *,
    payload_kg: NDArray[np.float64] | float = 0.0,
    compliance_joints: Sequence[int] = COMPLIANCE_JOINTS,
    offset_joints: Sequence[int] = ALL_JOINTS,
    point_mm: NDArray[np.float64] | Sequence[float] | None = None,
    rtol: float = 1e-8,
    max_iter: int = 100,
) -> PointConstraintFit:
    """Zero offsets (and compliance) from poses whose laser lines all pass through one point.

    ``a_deg`` (n, 6): commanded axis values of the poses in which the beam hit the PSD centre.
    The point is an unknown (the paper's method) unless ``point_mm`` gives it (a PSD surveyed in
    the robot base frame; then ``theta1`` is identifiable). Unidentifiable unknowns (``theta1``
    when the point is unknown) are removed by name; see ``fit.report``.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    cj = joint_numbers(compliance_joints, "compliance_joints")
    oj = joint_numbers(offset_joints, "offset_joints")
    known = None if point_mm is None else finite_array(point_mm, (3,), "point_mm")
    mass = MassModel.from_robot(robot)
    nominal = KinematicParams.from_robot(robot)
    names = [*(f"theta{j}" for j in oj), *(f"C{j}" for j in cj)]
    if known is None:
        names += ["P_x", "P_y", "P_z"]
    n_th, n_c = len(oj), len(cj)
    n_x = len(names)

    def unpack(x: NDArray[np.float64]) -> tuple[KinematicParams, NDArray[np.float64], NDArray[np.float64]]:
        dx = np.zeros(N_PARAMS)
        for k, j in enumerate(oj):
            dx[joint_param_index("theta", j)] = x[k]
        comp = np.zeros(N_JOINTS)
        for k, j in enumerate(cj):
            comp[j - 1] = x[n_th + k]
        return nominal.apply(dx), comp, (x[n_th + n_c :] if known is None else known)

    if known is None:
        ln0 = _lines(mass, nominal, np.zeros(N_JOINTS), a, mount, payload_kg)
        p0 = _intersection_point(ln0.o, ln0.u)
        x_full = np.concatenate([np.zeros(n_th + n_c), p0])
        priority = [*names[-3:], *names[:-3]]
    else:
        p0 = known
        x_full = np.zeros(n_x)
        priority = None
    # identifiability is structural: judge it on a consistent set of lines (the data's poses moved
    # minimally so that the nominal lines meet at p0), the point offered first, so that a turn of
    # the whole set-up about the base axis is charged to theta1
    a_c = _consistent_poses(mass, nominal, a, mount, p0, payload_kg)
    ln_c = _lines(mass, nominal, np.zeros(N_JOINTS), a_c, mount, payload_kg)
    jac_c = _point_jacobian(ln_c, p0, oj, cj)[:, :, :n_x]
    report = analyze_identifiability(jac_c, names, priority=priority, rtol=rtol)
    keep = report.identifiable_index

    def expand(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        out = x_full.copy()
        out[keep] = xk
        return out

    def lines_at(xk: NDArray[np.float64]) -> tuple[_Lines, NDArray[np.float64]]:
        params, comp, point = unpack(expand(xk))
        return _lines(mass, params, comp, a, mount, payload_kg), point

    def residual(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        ln, point = lines_at(xk)
        return _point_residual(ln, point).reshape(-1)

    def jacobian(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        ln, point = lines_at(xk)
        return _point_jacobian(ln, point, oj, cj)[:, :, :n_x][:, :, keep].reshape(3 * n, keep.size)

    result = improved_lm(residual, jacobian, x_full[keep], x_scale="jac", max_iter=max_iter)
    params, comp, point = unpack(expand(result.x))
    model = ComplianceModel(robot, params.theta_offset_rad - nominal.theta_offset_rad, comp)
    values = result.x.copy()
    rms = float(np.sqrt(np.mean(np.sum(result.residual.reshape(n, 3) ** 2, axis=1))))
    fit = ComplianceFit(
        model=model,
        report=report,
        identified=tuple(names[i] for i in keep),
        values=values,
        std=standard_errors(result.jacobian, result.residual),
        lm=result,
        rms_mm=rms,
        n_rows=n,
    )
    return PointConstraintFit(fit=fit, point_mm=point.copy())


def psd_distance_errors_mm(
    model: ComplianceModel,
    a_deg: NDArray[np.float64],
    mount: LaserMount,
    psd_center_mm: NDArray[np.float64],
    psd_normal: NDArray[np.float64],
    payload_kg: NDArray[np.float64] | float = 0.0,
) -> NDArray[np.float64]:
    """(n,) distance (mm) from the PSD centre to where the model's laser line meets the PSD plane.

    Seed 004's distance error: the poses' joint angles, compensated by the model (zero offsets and
    compliance), give the model's beam; it is intersected with the PSD plane (through the centre,
    normal ``psd_normal``).
    """
    c = finite_array(psd_center_mm, (3,), "psd_center_mm")
    nrm = finite_array(psd_normal, (3,), "psd_normal")
    nrm = nrm / np.linalg.norm(nrm)
    o, u = laser_lines(model.mass, model.params, model.compliance_rad_per_nm, a_deg, mount, payload_kg)
    un = u @ nrm
    if np.any(np.abs(un) < 1e-9):
        raise ValueError("a laser line is parallel to the PSD plane")
    t = ((c - o) @ nrm) / un
    hit = o + u * t[:, None]
    return np.linalg.norm(hit - c, axis=1)


def line_distance_errors_mm(
    model: ComplianceModel,
    a_deg: NDArray[np.float64],
    mount: LaserMount,
    psd_center_mm: NDArray[np.float64],
    payload_kg: NDArray[np.float64] | float = 0.0,
) -> NDArray[np.float64]:
    """(n,) perpendicular distance (mm) from the PSD centre to the model's laser line.

    The residual of the point constraint with the point known; an alternative reading of the
    distance error (:func:`psd_distance_errors_mm` is the paper's: along the PSD plane).
    """
    c = finite_array(psd_center_mm, (3,), "psd_center_mm")
    o, u = laser_lines(model.mass, model.params, model.compliance_rad_per_nm, a_deg, mount, payload_kg)
    w = c - o
    return np.linalg.norm(w - u * np.einsum("ni,ni->n", u, w)[:, None], axis=1)
