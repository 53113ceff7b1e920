"""Compliance-aware zero-offset calibration of seed 004 (Spong's elastic joints, point constraint).

Model. Spong's elastic-joint robot (seed 004 §1, ref. [9]) puts a linear torsion spring between
each motor and its link; at rest the link lags the motor by the spring's deflection
``δθ_i = C_i·τ_i`` (eq. 2: ``C_i`` the compliance, rad/(N m); ``τ_i`` the static torque on joint
i). On the IRB 120 links 2 and 3 are by far the heaviest, so the gravity torques of the links
(and of a payload at the TCP) deflect joints 2 and 3 and the other joints' compliance is neglected
(eqs 3–20). The improved zero-offset model (seed 004 §2) is, per joint::

    theta_i = q_i + offset_i + Δθ_i                  joints 1, 4, 5, 6
    theta_i = q_i + offset_i + Δθ_i + C_i·τ_i        joints 2, 3 (``compliance_joints``)

with ``q = sign·A`` (the commanded axis values, rad), ``offset_i`` the nominal zero of the robot
file and ``Δθ_i`` the zero-offset error to calibrate. ``τ`` is
:func:`comp_daemon.kinematics.forward.gravity_torques_nm` at the commanded configuration — the
full static model, of which the paper's planar closed forms (``τ3 = G3·L2·cos(θ2+θ3)``,
``τ2 = G2·L1·cos θ2 + G3·(L3·cos θ2 + L2·cos(θ2+θ3))``, eqs 3–4, 13–14) are the in-plane
special case — exactly as the shared effects model computes it
(:mod:`comp_daemon.models.effects`, effect ``compliance``). Our ``τ`` is the torque gravity exerts
on the links (DH sign), so a compliant joint yields with it and ``C > 0``; the paper quotes its
simulated coefficients with the opposite torque sign (C2 = −5.921122e-05, C3 = −9.137836e-06
(N m)⁻¹), and we use their magnitudes. The original model is the same with no ``C``.

Identification, as the paper formulates it (point constraint, §3, after Liu et al. [13–15]): a
laser on the flange casts a line from ``o`` along ``u``; the robot is servoed in several poses
until the beam hits the centre of a position sensitive detector (PSD), so all lines pass through
one unknown point ``P``. Per pose the constraint residual is the part of ``P − o`` normal to the
beam, ``r = (I − uuᵀ)(P − o)`` (mm, rank 2). The unknowns are the ``Δθ``, the ``C`` and ``P``;
they are solved by the improved Levenberg–Marquardt method of seed 000
(:func:`comp_daemon.models.lm.improved_lm`) with the exact Jacobian::

    ∂o/∂θ_i = z_{i−1} × (o − p_{i−1}),   ∂u/∂θ_i = z_{i−1} × u
    ∂r/∂θ_i = −(I − uuᵀ)·∂o/∂θ_i − (∂u·uᵀ + u·∂uᵀ)(P − o),   ∂r/∂C_i = τ_i·∂r/∂θ_i,   ∂r/∂P = I − uuᵀ

Which unknowns the constraint can determine is decided by the identifiability analysis of
:mod:`comp_daemon.models.identifiability` on the Jacobian of a consistent set of lines: ``Δθ1`` is
not (a turn of the whole set-up, ``P`` included, about the vertical base axis), which is why the
paper's simulated zero offset of joint 1 is 0. Seed 004 calibrates on 7 poses at a time, repeats
this 30 times over its 210 calibration poses, and averages the 30 results.

Identification from tracker positions (our data sets): the TCP residual ``measured − model``
(mm) over the same unknowns without ``P``; if the data are in the tracker's frame the base frame is
registered first and refined with them (``Δθ1`` then goes, dependent on the base rotation).

Evaluation (the paper's): with the identified parameters, each validation pose's model laser line
is intersected with the PSD plane; its distance from the PSD centre is the *distance error*
(:func:`psd_distance_errors_mm`). Units: mm, rad, N m, kg; axis values in deg.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import chain, gravity_torques_nm, identification_jacobian, tcp_position_mm
from comp_daemon.kinematics.inverse import solve_ik
from comp_daemon.kinematics.params import (
    N_PARAMS,
    PARAM_NAMES,
    KinematicParams,
    axes_deg_to_q_rad,
    joint_param_index,
    q_rad_to_axes_deg,
)
from comp_daemon.kinematics.so3 import left_jacobian, rotvec_to_matrix, skew
from comp_daemon.models.base import ErrorModel, as_axes
from comp_daemon.models.effects import EffectParams, MassModel, twin_state, twin_tcp_mm
from comp_daemon.models.identifiability import IdentifiabilityReport, analyze_identifiability
from comp_daemon.models.lm import LMResult, improved_lm
from comp_daemon.models.registration import detect_frame, rigid_registration
from comp_daemon.robot.description import RobotDescription, load_robot

__all__ = [
    "COMPLIANCE_JOINTS",
    "SEED004_COMPLIANCE_RAD_PER_NM",
    "SEED004_ZERO_OFFSETS_DEG",
    "ComplianceFit",
    "ComplianceModel",
    "LaserMount",
    "PointConstraintFit",
    "PsdPoses",
    "PsdSetup",
    "Seed004Result",
    "TrackerResult",
    "average_models",
    "calibrate_compliance",
    "calibrate_point_constraint",
    "laser_lines",
    "point_constraint_jacobian",
    "psd_distance_errors_mm",
    "reproduce_seed004",
    "reproduce_seed004_tracker",
    "simulate_psd_poses",
]

N_JOINTS = 6
COMPLIANCE_JOINTS: tuple[int, ...] = (2, 3)
ALL_JOINTS: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
SEED004_ZERO_OFFSETS_DEG: tuple[float, ...] = (0.0, -1.0, -2.0, -1.0, 1.0, -2.0)
SEED004_COMPLIANCE_RAD_PER_NM: tuple[float, ...] = (0.0, 5.921122e-05, 9.137836e-06, 0.0, 0.0, 0.0)
FrameChoice = Literal["auto", "base", "tracker"]


def _joints(joints: Sequence[int], what: str) -> tuple[int, ...]:
    out = tuple(int(j) for j in joints)
    for j in out:
        if not 1 <= j <= N_JOINTS:
            raise ValueError(f"{what}: joints are numbered 1..6, got {j}")
    if len(set(out)) != len(out):
        raise ValueError(f"{what}: joint listed twice in {out}")
    return out


def _vec(value: Any, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    out = np.array(value, dtype=float)
    if out.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name}: values must be finite")
    return out


class ComplianceModel(ErrorModel):
    """Nominal geometry with calibrated zero offsets and joint compliance (seed 004)."""

    kind: ClassVar[str] = "compliance"

    def __init__(
        self,
        robot: RobotDescription,
        zero_offset_rad: NDArray[np.float64] | Sequence[float],
        compliance_rad_per_nm: NDArray[np.float64] | Sequence[float],
        world_T_base: NDArray[np.float64] | None = None,
        tool_xyz_mm: NDArray[np.float64] | Sequence[float] | None = None,
        registration: NDArray[np.float64] | None = None,
    ) -> None:
        self.robot = robot
        self.zero_offset_rad = _vec(zero_offset_rad, (N_JOINTS,), "zero_offset_rad")
        self.compliance_rad_per_nm = _vec(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
        self.world_T_base = np.eye(4) if world_T_base is None else _vec(world_T_base, (4, 4), "world_T_base")
        self.registration = np.eye(4) if registration is None else _vec(registration, (4, 4), "registration")
        nominal = KinematicParams.from_robot(robot)
        tool = nominal.tool_xyz_mm if tool_xyz_mm is None else _vec(tool_xyz_mm, (3,), "tool_xyz_mm")
        dx = np.zeros(N_PARAMS)
        dx[0:30:5] = self.zero_offset_rad
        dx[36:39] = tool - nominal.tool_xyz_mm
        self.params: KinematicParams = nominal.apply(dx).with_base(self.world_T_base)
        self.effects = EffectParams(compliance_rad_per_nm=self.compliance_rad_per_nm)
        self.mass = MassModel.from_robot(robot)

    def predict_tcp_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        payload = 0.0 if payload_kg is None else payload_kg
        return twin_tcp_mm(self.mass, self.params, self.effects, as_axes(a_deg), None, payload, None)

    def deflection_rad(
        self, a_deg: NDArray[np.float64], payload_kg: NDArray[np.float64] | float = 0.0
    ) -> NDArray[np.float64]:
        """(n, 6) joint deflections ``C·τ`` (rad, DH sign) at the commanded axis values."""
        st = twin_state(self.mass, self.params, self.effects, as_axes(a_deg), None, payload_kg, None)
        return self.compliance_rad_per_nm * st.tau_nm

    def ik_params(self) -> KinematicParams:
        return self.params

    def to_payload(self) -> dict[str, Any]:
        return {
            "zero_offset_rad": self.zero_offset_rad.tolist(),
            "compliance_rad_per_nm": self.compliance_rad_per_nm.tolist(),
            "world_T_base": self.world_T_base.tolist(),
            "tool_xyz_mm": self.params.tool_xyz_mm.tolist(),
        }

    @classmethod
    def from_payload(
        cls,
        robot: RobotDescription,
        payload: dict[str, Any],
        order: int | None,
        registration: NDArray[np.float64],
    ) -> ComplianceModel:
        try:
            return cls(
                robot,
                payload["zero_offset_rad"],
                payload["compliance_rad_per_nm"],
                np.array(payload["world_T_base"], dtype=float),
                payload["tool_xyz_mm"],
                registration,
            )
        except KeyError as exc:
            raise ValueError(f"compliance model: missing field {exc.args[0]!r}") from None


def average_models(models: Sequence[ComplianceModel]) -> ComplianceModel:
    """The model with the mean zero offsets and compliances of ``models`` (seed 004's averaging)."""
    if not models:
        raise ValueError("no models to average")
    first = models[0]
    return ComplianceModel(
        first.robot,
        np.mean([m.zero_offset_rad for m in models], axis=0),
        np.mean([m.compliance_rad_per_nm for m in models], axis=0),
        first.world_T_base,
        first.params.tool_xyz_mm,
        first.registration,
    )


# ---------------------------------------------------------------------------------------------
# identification from tracker positions
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ComplianceFit:
    """The result of :func:`calibrate_compliance` or of one point-constraint calibration."""

    model: ComplianceModel
    report: IdentifiabilityReport
    identified: tuple[str, ...]  # e.g. theta2..theta6, C2, C3 (+ base_*, tool_*, P_*)
    values: NDArray[np.float64]  # rad, rad/(N m), mm: increments from the start (P_*: the point)
    std: NDArray[np.float64]  # 1-sigma standard errors from the residual
    lm: LMResult
    rms_mm: float  # RMS of the 3-D residual per row (TCP error, or line-to-point distance)
    n_rows: int
    frame: Literal["base", "tracker"] = "base"

    def named_values(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.identified, self.values, strict=True)}


def _standard_errors(jac: NDArray[np.float64], residual: NDArray[np.float64]) -> NDArray[np.float64]:
    m, p = jac.shape
    if m <= p:
        return np.full(p, np.nan)
    s2 = float(residual @ residual) / (m - p)
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    sv = np.where(sv > 1e-14 * sv[0], sv, np.inf)
    return np.sqrt(s2 * np.sum((vt / sv[:, None]) ** 2, axis=0)) / norms


def calibrate_compliance(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    p_measured_mm: NDArray[np.float64],
    *,
    payload_kg: NDArray[np.float64] | float = 0.0,
    compliance_joints: Sequence[int] = COMPLIANCE_JOINTS,
    offset_joints: Sequence[int] = ALL_JOINTS,
    frame: FrameChoice = "auto",
    fit_tool: bool = False,
    rtol: float = 1e-8,
    max_iter: int = 100,
) -> ComplianceFit:
    """Zero offsets (and compliance of ``compliance_joints``; ``()`` = the original model) from TCPs.

    ``a_deg`` (n, 6) commanded axis values, ``p_measured_mm`` (n, 3) measured TCP positions in the
    robot base frame or the tracker's (``frame``: detected by default; a tracker frame is registered
    and its six parameters refined too). ``fit_tool`` adds the tool xyz to the unknowns.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    p_meas = np.asarray(p_measured_mm, dtype=float)
    if p_meas.shape != (n, 3):
        raise ValueError(f"measured positions must have shape ({n}, 3), got {p_meas.shape}")
    if not np.all(np.isfinite(p_meas)):
        raise ValueError("measured positions must be finite")
    cj = _joints(compliance_joints, "compliance_joints")
    oj = _joints(offset_joints, "offset_joints")
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    nominal = KinematicParams.from_robot(robot)
    p_nominal = tcp_position_mm(nominal, axes_deg_to_q_rad(a, nominal.sign))
    chosen: Literal["base", "tracker"] = detect_frame(p_nominal, p_meas) if frame == "auto" else frame
    registration = rigid_registration(p_nominal, p_meas) if chosen == "tracker" else np.eye(4)
    mass = MassModel.from_robot(robot)

    geo_names = [f"theta{j}" for j in oj]
    if chosen == "tracker":
        geo_names = [*PARAM_NAMES[30:36], *geo_names]
    if fit_tool:
        geo_names += list(PARAM_NAMES[36:39])
    geo_idx = np.array([PARAM_NAMES.index(nm) for nm in geo_names], dtype=np.intp)
    c_names = [f"C{j}" for j in cj]
    all_names = [*geo_names, *c_names]

    def unpack(x: NDArray[np.float64]) -> tuple[KinematicParams, NDArray[np.float64], NDArray[np.float64]]:
        dx = np.zeros(N_PARAMS)
        dx[geo_idx] = x[: geo_idx.size]
        comp = np.zeros(N_JOINTS)
        for k, j in enumerate(cj):
            comp[j - 1] = x[geo_idx.size + k]
        start = nominal.with_base(registration)
        return start.apply(dx), comp, dx

    def tcp_and_jac(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        params, comp, dx = unpack(x)
        # the twin of the model (torques at the commanded configuration, as in predict_tcp_mm)
        st = twin_state(mass, params, EffectParams(compliance_rad_per_nm=comp), a, None, payload, None)
        ch = st.chain
        tau = st.tau_nm
        if not cj or not np.any(comp != 0.0):
            q_cmd = params.sign * np.deg2rad(a)
            tau = gravity_torques_nm(params, q_cmd, mass.link_mass_kg, mass.link_com_mm, payload)
        jac_all = identification_jacobian(params, st.q_rad, ch)
        jac_all[:, :, 33:36] = -skew(ch.tcp_mm - dx[30:33]) @ left_jacobian(dx[33:36])
        cols = [jac_all[:, :, geo_idx]]
        cols += [
            jac_all[:, :, joint_param_index("theta", j)][:, :, None] * tau[:, None, j - 1, None] for j in cj
        ]
        return ch.tcp_mm, np.concatenate(cols, axis=2)

    x0 = np.zeros(len(all_names))
    _, jac0 = tcp_and_jac(x0)
    report = analyze_identifiability(jac0, all_names, rtol=rtol)
    keep = report.identifiable_index
    x_full = np.zeros(len(all_names))

    def expand(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        out = x_full.copy()
        out[keep] = xk
        return out

    def residual(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        tcp, _ = tcp_and_jac(expand(xk))
        return (tcp - p_meas).reshape(-1)

    def jacobian(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        _, jac = tcp_and_jac(expand(xk))
        return jac[:, :, keep].reshape(3 * n, keep.size)

    result = improved_lm(residual, jacobian, np.zeros(keep.size), x_scale="jac", max_iter=max_iter)
    params, comp, _ = unpack(expand(result.x))
    offsets = params.theta_offset_rad - nominal.theta_offset_rad
    model = ComplianceModel(robot, offsets, comp, params.world_T_base, params.tool_xyz_mm, registration)
    rms = float(np.sqrt(np.mean(np.sum(result.residual.reshape(n, 3) ** 2, axis=1))))
    return ComplianceFit(
        model=model,
        report=report,
        identified=tuple(all_names[i] for i in keep),
        values=result.x.copy(),
        std=_standard_errors(result.jacobian, result.residual),
        lm=result,
        rms_mm=rms,
        n_rows=n,
        frame=chosen,
    )


# ---------------------------------------------------------------------------------------------
# point constraint (laser lines through one point, seed 004 §3)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class LaserMount:
    """The laser on the flange: beam origin (mm) and unit direction, both in the flange frame."""

    origin_mm: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 40.0, 60.0]))
    direction: NDArray[np.float64] = field(
        default_factory=lambda: np.array([np.sin(np.deg2rad(20.0)), 0.0, np.cos(np.deg2rad(20.0))])
    )

    def __post_init__(self) -> None:
        o = _vec(self.origin_mm, (3,), "LaserMount.origin_mm")
        u = _vec(self.direction, (3,), "LaserMount.direction")
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
    comp = _vec(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
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
    comp = _vec(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
    point = _vec(point_mm, (3,), "point_mm")
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
    rtol: float = 1e-8,
    max_iter: int = 100,
) -> PointConstraintFit:
    """Zero offsets (and compliance) from poses whose laser lines all pass through one point.

    ``a_deg`` (n, 6): commanded axis values of the poses in which the beam hit the PSD centre.
    Unidentifiable unknowns (``theta1`` always) are removed by name; see ``fit.report``.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    cj = _joints(compliance_joints, "compliance_joints")
    oj = _joints(offset_joints, "offset_joints")
    mass = MassModel.from_robot(robot)
    nominal = KinematicParams.from_robot(robot)
    names = [*(f"theta{j}" for j in oj), *(f"C{j}" for j in cj), "P_x", "P_y", "P_z"]
    n_th, n_c = len(oj), len(cj)

    def unpack(x: NDArray[np.float64]) -> tuple[KinematicParams, NDArray[np.float64], NDArray[np.float64]]:
        dx = np.zeros(N_PARAMS)
        for k, j in enumerate(oj):
            dx[joint_param_index("theta", j)] = x[k]
        comp = np.zeros(N_JOINTS)
        for k, j in enumerate(cj):
            comp[j - 1] = x[n_th + k]
        return nominal.apply(dx), comp, x[n_th + n_c :]

    ln0 = _lines(mass, nominal, np.zeros(N_JOINTS), a, mount, payload_kg)
    p0 = _intersection_point(ln0.o, ln0.u)
    x_full = np.concatenate([np.zeros(n_th + n_c), p0])
    # identifiability is structural: judge it on a consistent set of lines (the data's poses moved
    # minimally so that the nominal lines meet at p0), the point offered first, so that a turn of
    # the whole set-up about the base axis is charged to theta1
    a_c = _consistent_poses(mass, nominal, a, mount, p0, payload_kg)
    ln_c = _lines(mass, nominal, np.zeros(N_JOINTS), a_c, mount, payload_kg)
    priority = [*names[-3:], *names[:-3]]
    report = analyze_identifiability(_point_jacobian(ln_c, p0, oj, cj), names, priority=priority, rtol=rtol)
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
        return _point_jacobian(ln, point, oj, cj)[:, :, keep].reshape(3 * n, keep.size)

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
        std=_standard_errors(result.jacobian, result.residual),
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
    c = _vec(psd_center_mm, (3,), "psd_center_mm")
    nrm = _vec(psd_normal, (3,), "psd_normal")
    nrm = nrm / np.linalg.norm(nrm)
    o, u = laser_lines(model.mass, model.params, model.compliance_rad_per_nm, a_deg, mount, payload_kg)
    un = u @ nrm
    if np.any(np.abs(un) < 1e-9):
        raise ValueError("a laser line is parallel to the PSD plane")
    t = ((c - o) @ nrm) / un
    hit = o + u * t[:, None]
    return np.linalg.norm(hit - c, axis=1)


# ---------------------------------------------------------------------------------------------
# simulation of the paper's experiment
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class PsdSetup:
    """A PSD in the workspace and how the poses aim at it (robot base frame, mm)."""

    center_mm: NDArray[np.float64] = field(default_factory=lambda: np.array([380.0, 0.0, 120.0]))
    normal: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    mount: LaserMount = field(default_factory=LaserMount)
    standoff_mm: tuple[float, float] = (90.0, 220.0)
    cone_deg: float = 35.0  # beam directions within this angle of −normal
    seed_deg: tuple[float, ...] = (0.0, 10.0, 20.0, 0.0, 60.0, 0.0)  # IK seed (a wrist-down pose)


@dataclass(frozen=True, slots=True)
class PsdPoses:
    """Simulated point-constraint poses: commanded axis values and the link-5 noise of each."""

    a_deg: NDArray[np.float64]  # (n, 6)
    link5_delta_mm: NDArray[np.float64]  # (n, 2): added to a5 and d5 of the true robot for that pose


def _perpendicular(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """A unit vector perpendicular to the unit vector ``v`` (3,)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    w = np.cross(v, helper)
    return w / np.linalg.norm(w)


def _align(u_from: NDArray[np.float64], u_to: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3, 3) rotations taking the unit vector ``u_from`` (3,) onto each row of ``u_to`` (n, 3)."""
    axis = np.cross(u_from, u_to)
    s = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(s, u_to @ u_from)
    unit = axis / np.where(s > 1e-12, s, 1.0)[:, None]
    unit[s <= 1e-12] = _perpendicular(u_from)  # parallel: angle 0; antiparallel: a half turn
    return rotvec_to_matrix(unit * angle[:, None])


def _link5_shift(
    params: KinematicParams, q_rad: NDArray[np.float64], delta: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(n, 3) move of every point beyond link 5 when a5 += delta[:, 0] and d5 += delta[:, 1].

    ``d5`` translates along z of frame 4, ``a5`` along x after ``Rz(θ5)``; neither turns anything.
    """
    ch = chain(params, q_rad)
    return delta[:, 0, None] * ch.x_prime[:, 4] + delta[:, 1, None] * ch.world_T_frame[:, 4, :3, 2]


def simulate_psd_poses(
    robot: RobotDescription,
    true_params: KinematicParams,
    true_compliance_rad_per_nm: NDArray[np.float64] | Sequence[float],
    setup: PsdSetup,
    n: int,
    rng: np.random.Generator,
    *,
    link5_noise_mm: float = 1.0,
    payload_kg: float = 0.0,
    max_rounds: int = 20,
) -> PsdPoses:
    """Poses of the true robot whose laser line passes through the PSD centre (seed 004 §3).

    Before each pose the true robot's a5 and d5 get a fresh random error ``link5_noise_mm·U(0, 1)``
    (the paper's noise source); the beam direction is drawn within ``setup.cone_deg`` of the PSD's
    inward normal, the roll about it uniformly, the stand-off in ``setup.standoff_mm``. The true
    joints sit at ``q + C·τ(q)`` of the commanded ``q``, as in :mod:`comp_daemon.models.effects`.
    """
    comp = _vec(true_compliance_rad_per_nm, (N_JOINTS,), "true_compliance_rad_per_nm")
    mass = MassModel.from_robot(robot)
    mount = setup.mount
    nrm = setup.normal / np.linalg.norm(setup.normal)
    lim = np.sort(np.deg2rad(robot.axis_limits_deg) * robot.sign[:, None], axis=1)
    ik_params = KinematicParams(
        theta_offset_rad=true_params.theta_offset_rad,
        d_mm=true_params.d_mm,
        a_mm=true_params.a_mm,
        alpha_rad=true_params.alpha_rad,
        beta_rad=true_params.beta_rad,
        sign=true_params.sign,
        tool_xyz_mm=mount.origin_mm,
        world_T_base=true_params.world_T_base,
    )
    seed_q = axes_deg_to_q_rad(np.asarray(setup.seed_deg, dtype=float), robot.sign)
    found_a: list[NDArray[np.float64]] = []
    found_d: list[NDArray[np.float64]] = []
    have = 0
    for _ in range(max_rounds):
        m = 2 * (n - have) + 8
        # beam directions: uniform on the spherical cap around −normal
        cos_max = np.cos(np.deg2rad(setup.cone_deg))
        cz = 1.0 - rng.random(m) * (1.0 - cos_max)
        phi = rng.uniform(0.0, 2.0 * np.pi, m)
        sz = np.sqrt(1.0 - cz**2)
        e1 = _perpendicular(nrm)
        e2 = np.cross(nrm, e1)
        u = -cz[:, None] * nrm + sz[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        standoff = rng.uniform(*setup.standoff_mm, m)
        roll = rng.uniform(-np.pi, np.pi, m)
        r_f = rotvec_to_matrix(u * roll[:, None]) @ _align(mount.direction, u)
        target_o = setup.center_mm - standoff[:, None] * u
        delta = link5_noise_mm * rng.random((m, 2))
        q = np.repeat(seed_q[None, :], m, axis=0)
        shift = np.zeros((m, 3))
        ok = np.ones(m, dtype=bool)
        for _k in range(4):  # the beam origin moves with the link-5 error: aim so that it lands
            res = solve_ik(ik_params, lim, target_o - shift, r_f, q, tol_mm=1e-10, tol_rad=1e-13)
            q, ok = res.q_rad, res.ok
            shift = _link5_shift(ik_params, q, delta)
        q_act = q
        q_cmd = q_act.copy()
        for _k in range(30):  # commanded q with q_cmd + C·τ(q_cmd) = q_act
            tau = gravity_torques_nm(true_params, q_cmd, mass.link_mass_kg, mass.link_com_mm, payload_kg)
            q_next = q_act - comp * tau
            done = np.max(np.abs(q_next - q_cmd)) < 1e-15
            q_cmd = q_next
            if done:
                break
        a_cmd = q_rad_to_axes_deg(q_cmd, robot.sign)
        within = np.all(
            (a_cmd >= robot.axis_limits_deg[:, 0]) & (a_cmd <= robot.axis_limits_deg[:, 1]), axis=1
        )
        good = ok & within
        found_a.append(a_cmd[good])
        found_d.append(delta[good])
        have += int(good.sum())
        if have >= n:
            return PsdPoses(a_deg=np.concatenate(found_a)[:n], link5_delta_mm=np.concatenate(found_d)[:n])
    raise ValueError(f"only {have} of {n} PSD poses are reachable; move the PSD or narrow the cone")


@dataclass(frozen=True, slots=True)
class Seed004Result:
    """Mean distance errors (mm) on the validation poses, seed 004's simulation and ours."""

    n_fit: int
    n_check: int
    poses_per_calibration: int
    uncompensated_mm: float
    zero_offset_mm: float  # the original model, averaged over the calibrations (the paper's way)
    compliance_mm: float  # the improved model, averaged likewise
    zero_offset_joint_mm: float  # one calibration on all fit poses (not in the paper)
    compliance_joint_mm: float
    zero_offset_model: ComplianceModel
    compliance_model: ComplianceModel
    true_offsets_rad: NDArray[np.float64]
    true_compliance_rad_per_nm: NDArray[np.float64]

    def table(self) -> dict[str, Any]:
        deg = np.rad2deg
        return {
            "rows": {"fit": self.n_fit, "check": self.n_check},
            "poses_per_calibration": self.poses_per_calibration,
            "mean_distance_error_mm": {
                "uncompensated": round(self.uncompensated_mm, 4),
                "zero_offset_averaged": round(self.zero_offset_mm, 4),
                "compliance_averaged": round(self.compliance_mm, 4),
                "zero_offset_all_poses": round(self.zero_offset_joint_mm, 4),
                "compliance_all_poses": round(self.compliance_joint_mm, 4),
            },
            "paper_mm": {"zero_offset": 0.9692, "compliance": 0.5772},
            "true": {
                "zero_offset_deg": deg(self.true_offsets_rad).round(4).tolist(),
                "C2_C3_rad_per_nm": self.true_compliance_rad_per_nm[1:3].tolist(),
            },
            "compliance_model": {
                "zero_offset_deg": deg(self.compliance_model.zero_offset_rad).round(4).tolist(),
                "C2_C3_rad_per_nm": self.compliance_model.compliance_rad_per_nm[1:3].tolist(),
            },
            "zero_offset_model": {
                "zero_offset_deg": deg(self.zero_offset_model.zero_offset_rad).round(4).tolist()
            },
        }


def reproduce_seed004(
    *,
    robot: RobotDescription | None = None,
    seed: int = 0,
    n_poses: int = 420,
    n_fit: int = 210,
    poses_per_calibration: int = 7,
    link5_noise_mm: float = 1.0,
    setup: PsdSetup | None = None,
    zero_offsets_deg: Sequence[float] = SEED004_ZERO_OFFSETS_DEG,
    compliance_rad_per_nm: Sequence[float] = SEED004_COMPLIANCE_RAD_PER_NM,
) -> Seed004Result:
    """Seed 004's simulation: 420 point-constraint poses of an IRB 120 with zero-offset errors
    (0, −1, −2, −1, 1, −2)°, compliance C2, C3 and link-5 noise; 210 calibrate (7 at a time, the
    results averaged), 210 validate by the PSD distance error."""
    robot = robot if robot is not None else load_robot("irb120")
    setup = setup if setup is not None else PsdSetup()
    if not 0 < n_fit < n_poses:
        raise ValueError(f"need 0 < n_fit < n_poses, got {n_fit}, {n_poses}")
    if poses_per_calibration < 4 or n_fit % poses_per_calibration:
        raise ValueError(f"n_fit ({n_fit}) must be a multiple of poses_per_calibration (>= 4)")
    rng = np.random.default_rng(seed)
    offsets = np.deg2rad(np.asarray(zero_offsets_deg, dtype=float))
    comp_true = _vec(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
    dx = np.zeros(N_PARAMS)
    dx[0:30:5] = offsets
    true_params = KinematicParams.from_robot(robot).apply(dx)
    poses = simulate_psd_poses(
        robot, true_params, comp_true, setup, n_poses, rng, link5_noise_mm=link5_noise_mm
    )
    a_fit, a_chk = poses.a_deg[:n_fit], poses.a_deg[n_fit:]

    def evaluate(model: ComplianceModel) -> float:
        err = psd_distance_errors_mm(model, a_chk, setup.mount, setup.center_mm, setup.normal)
        return float(err.mean())

    groups = a_fit.reshape(-1, poses_per_calibration, 6)
    zero = average_models(
        [calibrate_point_constraint(robot, g, setup.mount, compliance_joints=()).model for g in groups]
    )
    comp = average_models([calibrate_point_constraint(robot, g, setup.mount).model for g in groups])
    zero_all = calibrate_point_constraint(robot, a_fit, setup.mount, compliance_joints=()).model
    comp_all = calibrate_point_constraint(robot, a_fit, setup.mount).model
    nominal = ComplianceModel(robot, np.zeros(N_JOINTS), np.zeros(N_JOINTS))
    return Seed004Result(
        n_fit=n_fit,
        n_check=n_poses - n_fit,
        poses_per_calibration=poses_per_calibration,
        uncompensated_mm=evaluate(nominal),
        zero_offset_mm=evaluate(zero),
        compliance_mm=evaluate(comp),
        zero_offset_joint_mm=evaluate(zero_all),
        compliance_joint_mm=evaluate(comp_all),
        zero_offset_model=zero,
        compliance_model=comp,
        true_offsets_rad=offsets,
        true_compliance_rad_per_nm=comp_true,
    )


@dataclass(frozen=True, slots=True)
class TrackerResult:
    """Seed 004's comparison on tracker data: mean 3-D TCP error (mm) on the check rows."""

    n_fit: int
    n_check: int
    uncompensated_mm: float
    zero_offset_mm: float
    compliance_mm: float
    zero_offset_fit: ComplianceFit
    compliance_fit: ComplianceFit

    def table(self) -> dict[str, Any]:
        return {
            "rows": {"fit": self.n_fit, "check": self.n_check},
            "mean_tcp_error_mm": {
                "uncompensated": round(self.uncompensated_mm, 4),
                "zero_offset": round(self.zero_offset_mm, 4),
                "compliance": round(self.compliance_mm, 4),
            },
            "compliance_fit": {
                "zero_offset_deg": np.rad2deg(self.compliance_fit.model.zero_offset_rad).round(4).tolist(),
                "C2_C3_rad_per_nm": self.compliance_fit.model.compliance_rad_per_nm[1:3].tolist(),
                "removed": list(self.compliance_fit.report.removed_names()),
            },
        }


SEED004_TRACKER_AXES_DEG: tuple[tuple[float, float], ...] = (
    (-60.0, 60.0),
    (-30.0, 70.0),
    (-60.0, 50.0),
    (-90.0, 90.0),
    (-90.0, 90.0),
    (-180.0, 180.0),
)


def reproduce_seed004_tracker(
    *,
    robot: RobotDescription | None = None,
    seed: int = 0,
    n_poses: int = 420,
    n_fit: int = 210,
    tracker_sigma_mm: float = 0.01,
    payload_kg: Sequence[float] = (0.0, 3.0),
    zero_offsets_deg: Sequence[float] = SEED004_ZERO_OFFSETS_DEG,
    compliance_rad_per_nm: Sequence[float] = SEED004_COMPLIANCE_RAD_PER_NM,
) -> TrackerResult:
    """Seed 004's robot (IRB 120, same zero offsets and compliance) measured by a tracker instead.

    Axis values uniform in :data:`SEED004_TRACKER_AXES_DEG`, each pose with one of ``payload_kg``
    at the TCP, tracker noise σ per axis; the first ``n_fit`` rows fit, the rest check.
    """
    robot = robot if robot is not None else load_robot("irb120")
    if not 0 < n_fit < n_poses:
        raise ValueError(f"need 0 < n_fit < n_poses, got {n_fit}, {n_poses}")
    rng = np.random.default_rng(seed)
    box = np.array(SEED004_TRACKER_AXES_DEG)
    a = box[:, 0] + rng.random((n_poses, N_JOINTS)) * (box[:, 1] - box[:, 0])
    payload = rng.choice(np.asarray(payload_kg, dtype=float), n_poses)
    truth = ComplianceModel(
        robot, np.deg2rad(np.asarray(zero_offsets_deg, dtype=float)), compliance_rad_per_nm
    )
    p = truth.predict_tcp_mm(a, None, payload) + rng.normal(0.0, tracker_sigma_mm, (n_poses, 3))
    fit, chk = slice(0, n_fit), slice(n_fit, n_poses)
    zero = calibrate_compliance(
        robot, a[fit], p[fit], payload_kg=payload[fit], compliance_joints=(), frame="base"
    )
    comp = calibrate_compliance(robot, a[fit], p[fit], payload_kg=payload[fit], frame="base")

    def mean_err(model: ErrorModel) -> float:
        return float(np.linalg.norm(p[chk] - model.predict_tcp_mm(a[chk], None, payload[chk]), axis=1).mean())

    nominal = ComplianceModel(robot, np.zeros(N_JOINTS), np.zeros(N_JOINTS))
    return TrackerResult(
        n_fit=n_fit,
        n_check=n_poses - n_fit,
        uncompensated_mm=mean_err(nominal),
        zero_offset_mm=mean_err(zero.model),
        compliance_mm=mean_err(comp.model),
        zero_offset_fit=zero,
        compliance_fit=comp,
    )


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m comp_daemon.models.compliance``: seed 004's simulation (and the tracker variant)."""
    parser = argparse.ArgumentParser(description="Reproduce seed 004's zero-offset calibration simulation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--noise-mm",
        type=float,
        nargs="+",
        default=[0.1, 0.3, 1.0],
        help="scales of the a5/d5 noise U(0,1) to run (mm)",
    )
    parser.add_argument("--poses", type=int, default=420)
    parser.add_argument("--fit", type=int, default=210)
    args = parser.parse_args(argv)
    out: dict[str, Any] = {"psd": {}}
    for noise in args.noise_mm:
        result = reproduce_seed004(seed=args.seed, link5_noise_mm=noise, n_poses=args.poses, n_fit=args.fit)
        out["psd"][f"noise_{noise:g}_mm"] = result.table()
    out["tracker"] = reproduce_seed004_tracker(seed=args.seed, n_poses=args.poses, n_fit=args.fit).table()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
