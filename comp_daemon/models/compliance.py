"""Compliance-aware zero-offset calibration of seed 004 (Spong's elastic joints) from TCP positions.

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

Identification from tracker positions (our data sets, :func:`calibrate_compliance`): the TCP
residual ``measured − model`` (mm) over the ``Δθ`` and the ``C``, solved by the improved
Levenberg–Marquardt method of seed 000 (:func:`comp_daemon.estimation.lm.improved_lm`) on the unknowns
the identifiability analysis keeps; if the data are in the tracker's frame the base frame is
registered first and refined with them (``Δθ1`` then goes, dependent on the base rotation).

With ``geometry=True`` every MDH parameter, the base frame and the tool are unknowns beside the
``C`` (the kinematic calibration of seed 000 with the compliance; dependent parameters removed by
name in the MDH priority): the registry's ``compliance`` kind (``KIND``, :func:`fit_compliance_kind`),
the compliance kept only if it earns its place out of fold
(:func:`comp_daemon.models.fitting.select_effects`; always with ``compliance:all``). The paper's
form, zero offsets and ``C`` on the nominal geometry, is ``compliance:paper``.

The paper's own experiment (laser lines through a PSD, seed 004 §3) is reproduced by
``python -m benchmarks.seed004_compliance``. Units: mm, rad, N m, kg; axis values in deg.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.identifiability import (
    IdentifiabilityReport,
    analyze_identifiability,
    mdh_priority,
)
from comp_daemon.estimation.lm import LMResult, improved_lm
from comp_daemon.estimation.selection import keep_all
from comp_daemon.kinematics.forward import gravity_torques_nm, identification_jacobian
from comp_daemon.kinematics.params import (
    N_PARAMS,
    PARAM_NAMES,
    KinematicParams,
    joint_param_index,
)
from comp_daemon.kinematics.so3 import left_jacobian, skew
from comp_daemon.models.base import ErrorModel, Query, StoredModel, as_axes, finite_array, measured_positions
from comp_daemon.models.covariance import attach_covariance
from comp_daemon.models.effects import EffectParams, MassModel, TwinState, twin_state, twin_tcp_mm
from comp_daemon.models.fitting import (
    FitOptions,
    FittedModel,
    ModelSpec,
    identified_info,
    lm_info,
    report_info,
    select_effects,
)
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.kinematic import mdh_payload, params_from_payload, registered_start
from comp_daemon.models.kinematic_kind import KINEMATIC_PARAMETERS
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "ALL_JOINTS",
    "COMPLIANCE_JOINTS",
    "KIND",
    "N_JOINTS",
    "ComplianceFit",
    "ComplianceModel",
    "calibrate_compliance",
    "compliance_jacobian",
    "compliance_parameters",
    "fit_compliance_kind",
    "joint_numbers",
    "standard_errors",
]

N_JOINTS = 6
COMPLIANCE_JOINTS: tuple[int, ...] = (2, 3)
ALL_JOINTS: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
FrameChoice = Literal["auto", "base", "tracker"]


def joint_numbers(joints: Sequence[int], what: str) -> tuple[int, ...]:
    """Joint numbers 1..6, each once (ValueError naming ``what``)."""
    out = tuple(int(j) for j in joints)
    for j in out:
        if not 1 <= j <= N_JOINTS:
            raise ValueError(f"{what}: joints are numbered 1..6, got {j}")
    if len(set(out)) != len(out):
        raise ValueError(f"{what}: joint listed twice in {out}")
    return out


class ComplianceModel(ErrorModel):
    """Joint compliance (seed 004) on calibrated zero offsets (the paper's form, nominal geometry
    otherwise) or on a whole calibrated MDH geometry (``geometry``)."""

    kind: ClassVar[str] = "compliance"

    def __init__(
        self,
        robot: RobotDescription,
        zero_offset_rad: NDArray[np.float64] | Sequence[float],
        compliance_rad_per_nm: NDArray[np.float64] | Sequence[float],
        world_T_base: NDArray[np.float64] | None = None,
        tool_xyz_mm: NDArray[np.float64] | Sequence[float] | None = None,
        registration: NDArray[np.float64] | None = None,
        geometry: KinematicParams | None = None,
    ) -> None:
        self.robot = robot
        self.zero_offset_rad = finite_array(zero_offset_rad, (N_JOINTS,), "zero_offset_rad")
        self.compliance_rad_per_nm = finite_array(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
        self.world_T_base = (
            np.eye(4) if world_T_base is None else finite_array(world_T_base, (4, 4), "world_T_base")
        )
        self.registration = (
            np.eye(4) if registration is None else finite_array(registration, (4, 4), "registration")
        )
        nominal = KinematicParams.from_robot(robot)
        tool = nominal.tool_xyz_mm if tool_xyz_mm is None else finite_array(tool_xyz_mm, (3,), "tool_xyz_mm")
        self.geometric = geometry is not None
        if geometry is not None:
            self.params: KinematicParams = geometry
            self.world_T_base = geometry.world_T_base
            self.zero_offset_rad = geometry.theta_offset_rad - nominal.theta_offset_rad
        else:
            dx = np.zeros(N_PARAMS)
            dx[0:30:5] = self.zero_offset_rad
            dx[36:39] = tool - nominal.tool_xyz_mm
            self.params = nominal.apply(dx).with_base(self.world_T_base)
        self.effects = EffectParams(compliance_rad_per_nm=self.compliance_rad_per_nm)
        self.mass = MassModel.from_robot(robot)

    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        return twin_tcp_mm(self.mass, self.params, self.effects, query.a, None, query.payload_kg, None)

    def parameter_jacobian(
        self, names: Sequence[str], values: NDArray[np.float64], query: Query
    ) -> NDArray[np.float64]:
        """The compliance calibration's Jacobian (:func:`compliance_jacobian`) at the query's poses."""
        return compliance_jacobian(self, names, values, query.a, query.payload_kg)

    def deflection_rad(
        self, a_deg: NDArray[np.float64], payload_kg: NDArray[np.float64] | float = 0.0
    ) -> NDArray[np.float64]:
        """(n, 6) joint deflections ``C·τ`` (rad, DH sign) at the commanded axis values."""
        st = twin_state(self.mass, self.params, self.effects, as_axes(a_deg), None, payload_kg, None)
        return self.compliance_rad_per_nm * st.tau_nm

    def ik_params(self) -> KinematicParams:
        return self.params

    def to_payload(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "zero_offset_rad": self.zero_offset_rad.tolist(),
            "compliance_rad_per_nm": self.compliance_rad_per_nm.tolist(),
            "world_T_base": self.world_T_base.tolist(),
            "tool_xyz_mm": self.params.tool_xyz_mm.tolist(),
        }
        if self.geometric:
            out["mdh"] = mdh_payload(self.params)
        return out

    @classmethod
    def from_stored(cls, stored: StoredModel) -> ComplianceModel:
        robot, payload = stored.robot, stored.payload
        try:
            geometry = None
            mdh = payload.get("mdh")
            if mdh is not None:
                geometry = params_from_payload(
                    robot, mdh, payload["tool_xyz_mm"], payload["world_T_base"], prefix="mdh."
                )
            return cls(
                robot,
                payload["zero_offset_rad"],
                payload["compliance_rad_per_nm"],
                np.array(payload["world_T_base"], dtype=float),
                payload["tool_xyz_mm"],
                stored.registration,
                geometry,
            )
        except KeyError as exc:
            raise ValueError(f"compliance model: missing field {exc.args[0]!r}") from None


@dataclass(frozen=True, slots=True)
class ComplianceFit:
    """The result of :func:`calibrate_compliance` (or of a point-constraint calibration)."""

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


def standard_errors(jac: NDArray[np.float64], residual: NDArray[np.float64]) -> NDArray[np.float64]:
    """1-sigma standard errors of least-squares unknowns from the Jacobian and the residual."""
    m, p = jac.shape
    if m <= p:
        return np.full(p, np.nan)
    s2 = float(residual @ residual) / (m - p)
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    sv = np.where(sv > 1e-14 * sv[0], sv, np.inf)
    return np.sqrt(s2 * np.sum((vt / sv[:, None]) ** 2, axis=0)) / norms


def _unpack(
    start: KinematicParams, geo_idx: NDArray[np.intp], cj: Sequence[int], x: NDArray[np.float64]
) -> tuple[KinematicParams, NDArray[np.float64], NDArray[np.float64]]:
    """Parameters, compliance (6,) and geometric increments of the unknowns ``x`` (geometric, then C)."""
    dx = np.zeros(N_PARAMS)
    dx[geo_idx] = x[: geo_idx.size]
    comp = np.zeros(N_JOINTS)
    for k, j in enumerate(cj):
        comp[j - 1] = x[geo_idx.size + k]
    return start.apply(dx), comp, dx


def _twin(
    mass: MassModel,
    params: KinematicParams,
    comp: NDArray[np.float64],
    a: NDArray[np.float64],
    payload: NDArray[np.float64] | float,
) -> TwinState:
    """The twin of the model (torques at the commanded configuration, as in predict_tcp_mm)."""
    return twin_state(mass, params, EffectParams(compliance_rad_per_nm=comp), a, None, payload, None)


def _tcp_and_jac(
    mass: MassModel,
    start: KinematicParams,
    geo_idx: NDArray[np.intp],
    cj: Sequence[int],
    x: NDArray[np.float64],
    a: NDArray[np.float64],
    payload: NDArray[np.float64] | float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """TCP (n, 3) and its derivative (n, 3, len(x)) w.r.t. the unknowns ``x`` of the calibration."""
    params, comp, dx = _unpack(start, geo_idx, cj, x)
    st = _twin(mass, params, comp, a, payload)
    ch = st.chain
    tau = st.tau_nm
    if not cj or not np.any(comp != 0.0):
        q_cmd = params.sign * np.deg2rad(a)
        tau = gravity_torques_nm(params, q_cmd, mass.link_mass_kg, mass.link_com_mm, payload)
    jac_all = identification_jacobian(params, st.q_rad, ch)
    jac_all[:, :, 33:36] = -skew(ch.tcp_mm - dx[30:33]) @ left_jacobian(dx[33:36])
    cols = [jac_all[:, :, geo_idx]]
    cols += [jac_all[:, :, joint_param_index("theta", j)][:, :, None] * tau[:, None, j - 1, None] for j in cj]
    return ch.tcp_mm, np.concatenate(cols, axis=2)


def compliance_jacobian(
    model: ComplianceModel,
    names: Sequence[str],
    values: NDArray[np.float64],
    a_deg: NDArray[np.float64],
    payload_kg: NDArray[np.float64] | float = 0.0,
) -> NDArray[np.float64]:
    """(n, 3, p) derivative of the model's TCP at ``a_deg`` w.r.t. its calibration's identified
    parameters ``names`` (geometric increments, then ``C{j}``) at their ``values``."""
    a = as_axes(a_deg)
    geo = [nm for nm in names if nm in PARAM_NAMES]
    c_names = [nm for nm in names if nm not in PARAM_NAMES]
    if list(names) != geo + c_names or any(not (nm.startswith("C") and nm[1:].isdigit()) for nm in c_names):
        raise ValueError(f"compliance parameters must be geometric names then C1..C6, got {list(names)}")
    geo_idx = np.array([PARAM_NAMES.index(nm) for nm in geo], dtype=np.intp)
    cj = [int(nm[1:]) for nm in c_names]
    start = KinematicParams.from_robot(model.robot).with_base(model.registration)
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (a.shape[0],))
    return _tcp_and_jac(model.mass, start, geo_idx, cj, np.asarray(values, dtype=float), a, payload)[1]


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
    geometry: bool = False,
    rtol: float = 1e-8,
    max_iter: int = 100,
) -> ComplianceFit:
    """Zero offsets (and compliance of ``compliance_joints``; ``()`` = the original model) from TCPs.

    ``a_deg`` (n, 6) commanded axis values, ``p_measured_mm`` (n, 3) measured TCP positions in the
    robot base frame or the tracker's (``frame``: detected by default; a tracker frame is registered
    and its six parameters refined too). ``fit_tool`` adds the tool xyz to the unknowns;
    ``geometry`` makes every MDH parameter, the base frame and the tool unknowns (the kinematic
    calibration of seed 000 with the compliance beside it; dependent parameters removed by name in
    the MDH priority), instead of the zero offsets alone.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    p_meas = measured_positions(p_measured_mm, n)
    cj = joint_numbers(compliance_joints, "compliance_joints")
    oj = joint_numbers(offset_joints, "offset_joints")
    payload = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
    start, chosen, registration = registered_start(robot, a, p_meas, frame)
    mass = MassModel.from_robot(robot)
    geo_names = _geometric_unknowns(oj, tracker=chosen == "tracker", fit_tool=fit_tool, geometry=geometry)
    geo_idx = np.array([PARAM_NAMES.index(nm) for nm in geo_names], dtype=np.intp)
    c_names = [f"C{j}" for j in cj]
    all_names = [*geo_names, *c_names]

    def unpack(x: NDArray[np.float64]) -> tuple[KinematicParams, NDArray[np.float64], NDArray[np.float64]]:
        return _unpack(start, geo_idx, cj, x)

    def tcp_and_jac(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return _tcp_and_jac(mass, start, geo_idx, cj, x, a, payload)

    x0 = np.zeros(len(all_names))
    _, jac0 = tcp_and_jac(x0)
    priority = mdh_priority(start, extra=c_names) if geometry else None
    report = analyze_identifiability(jac0, all_names, priority=priority, rtol=rtol)
    keep = report.identifiable_index
    x_full = np.zeros(len(all_names))

    def expand(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        out = x_full.copy()
        out[keep] = xk
        return out

    def residual(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        params, comp, _ = unpack(expand(xk))
        return (_twin(mass, params, comp, a, payload).tcp_mm - p_meas).reshape(-1)

    def jacobian(xk: NDArray[np.float64]) -> NDArray[np.float64]:
        _, jac = tcp_and_jac(expand(xk))
        return jac[:, :, keep].reshape(3 * n, keep.size)

    # the analysed Jacobian's identified columns are the iteration's first Jacobian
    first = jac0[:, :, keep].reshape(3 * n, keep.size)
    result = improved_lm(
        residual, jacobian, np.zeros(keep.size), x_scale="jac", max_iter=max_iter, jacobian_x0=first
    )
    params, comp, _ = unpack(expand(result.x))
    offsets = params.theta_offset_rad - start.theta_offset_rad  # the start's are the nominal zeros
    model = ComplianceModel(
        robot,
        offsets,
        comp,
        params.world_T_base,
        params.tool_xyz_mm,
        registration,
        params if geometry else None,
    )
    rms = float(np.sqrt(np.mean(np.sum(result.residual.reshape(n, 3) ** 2, axis=1))))
    return ComplianceFit(
        model=model,
        report=report,
        identified=tuple(all_names[i] for i in keep),
        values=result.x.copy(),
        std=standard_errors(result.jacobian, result.residual),
        lm=result,
        rms_mm=rms,
        n_rows=n,
        frame=chosen,
    )


def _geometric_unknowns(
    offset_joints: Sequence[int], *, tracker: bool, fit_tool: bool, geometry: bool
) -> list[str]:
    """The geometric unknowns beside the compliance: every one of :data:`PARAM_NAMES` with
    ``geometry``; else the zero offsets ``theta{j}`` of ``offset_joints``, after the base frame's six
    when the data are in the tracker's frame (its registration refined), and the tool's three with
    ``fit_tool``."""
    if geometry:
        return list(PARAM_NAMES)
    base = list(PARAM_NAMES[30:36]) if tracker else []
    tool = list(PARAM_NAMES[36:39]) if fit_tool else []
    return [*base, *(f"theta{j}" for j in offset_joints), *tool]


def fit_compliance_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """Seed 004's compliance of joints 2 and 3 under the rows' payloads, on the whole kinematic
    geometry (``compliance``; the compliance kept only if it earns its place, every time with
    ``:all``) or on the zero offsets alone (``compliance:paper``, the paper's form)."""
    geometry = not spec.paper

    def calibrate(effs: Sequence[str], sub: MeasuredRows, fo: FitOptions) -> ComplianceFit:
        return calibrate_compliance(
            robot,
            sub.a_deg,
            sub.xyz_mm,
            payload_kg=sub.payload_kg,
            compliance_joints=COMPLIANCE_JOINTS if "compliance" in effs else (),
            frame=fo.frame,
            geometry=geometry,
        )

    kept: tuple[str, ...] = ("compliance",)
    if spec.paper:
        selection = keep_all(kept)
    else:
        kept, selection = select_effects(
            robot, rows, spec, options, ("compliance",), lambda e, sub, fo: calibrate(e, sub, fo).model
        )
    cf = calibrate(kept, rows, options)
    attach_covariance(cf.model, cf.identified, cf.values, cf.lm.jacobian, cf.lm.residual)
    info = {
        "kind": spec.kind,
        "rows": rows.n,
        "form": "zero offsets and C2, C3 (seed 004)" if spec.paper else "kinematic geometry and C2, C3",
        "rms_mm": cf.rms_mm,
        "compliance_rad_per_nm": cf.model.compliance_rad_per_nm.tolist(),
        "zero_offset_rad": cf.model.zero_offset_rad.tolist(),
        "solver": lm_info(cf.lm),
        "identifiability": report_info(cf.report),
        "identified": identified_info(cf.identified, cf.values, cf.std),
        "selection": selection.to_info(),
    }
    return FittedModel(cf.model, cf.frame, info)


def compliance_parameters(spec: ModelSpec) -> int:
    """The geometry's parameters and C2, C3 (the paper's form: base frame, zero offsets, C2, C3)."""
    if spec.paper:
        return 6 + 6 + len(COMPLIANCE_JOINTS)
    return KINEMATIC_PARAMETERS + len(COMPLIANCE_JOINTS)


KIND = ModelKind(
    "compliance",
    "the kinematic geometry and joint compliance C2, C3 under the payload_kg of each row (seed 004);"
    " compliance:paper the paper's zero offsets and C2, C3 alone",
    ComplianceModel,
    fit_compliance_kind,
    compliance_parameters,
    option_words=("all", "paper"),
    uses=("payload_kg",),
)
