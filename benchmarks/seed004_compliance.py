"""Seed 004's simulation, repeated: zero-offset calibration with and without joint compliance.

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.seed004_compliance`` (JSON;
about 10 s). An IRB 120 with the paper's zero-offset errors and compliances C2, C3; 420 poses whose
true laser beams pass through the centre of a PSD (:func:`simulate_psd_poses`), 210 calibrate by
the point constraint (:mod:`benchmarks.seed004_point`: 7 poses at a time with the results averaged
as the paper does, and once on all of them), 210 validate by the PSD distance error; then the same
robot measured by a tracker and calibrated with the product's
:func:`comp_daemon.models.compliance.calibrate_compliance` (:func:`reproduce_seed004_tracker`).
The defaults are the paper's set-up; the options (``--help``) each change one of its assumptions
(noise kind, scale and block, poses per calibration, averaging, known point, error definition,
compliance joints and scale, payload, pose cone and stand-off); :mod:`benchmarks.seed004_variations`
tabulates them over seeds. Results and their discussion: ``docs/models-001-004.md``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from benchmarks.seed004_point import (
    LaserMount,
    calibrate_point_constraint,
    line_distance_errors_mm,
    psd_distance_errors_mm,
)
from comp_daemon.kinematics.forward import chain, gravity_torques_nm
from comp_daemon.kinematics.inverse import solve_ik
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad, q_rad_to_axes_deg
from comp_daemon.kinematics.so3 import rotvec_to_matrix
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.compliance import (
    COMPLIANCE_JOINTS,
    N_JOINTS,
    ComplianceFit,
    ComplianceModel,
    calibrate_compliance,
    finite_array,
)
from comp_daemon.models.effects import MassModel
from comp_daemon.robot.description import RobotDescription, load_robot

__all__ = [
    "SEED004_COMPLIANCE_RAD_PER_NM",
    "SEED004_TRACKER_AXES_DEG",
    "SEED004_ZERO_OFFSETS_DEG",
    "PsdPoses",
    "PsdSetup",
    "Seed004Result",
    "TrackerResult",
    "average_models",
    "main",
    "reproduce_seed004",
    "reproduce_seed004_tracker",
    "simulate_psd_poses",
]

NoiseKind = Literal["uniform", "centred"]
Averaging = Literal["mean", "median"]
ErrorKind = Literal["plane", "line"]

# seed 004's simulated robot: zero-offset errors (deg; the seed gives no unit) and the magnitudes of
# its compliances C2, C3 (rad/(N m); the paper quotes them negative, in the opposite torque sign)
SEED004_ZERO_OFFSETS_DEG: tuple[float, ...] = (0.0, -1.0, -2.0, -1.0, 1.0, -2.0)
SEED004_COMPLIANCE_RAD_PER_NM: tuple[float, ...] = (0.0, 5.921122e-05, 9.137836e-06, 0.0, 0.0, 0.0)


def average_models(models: Sequence[ComplianceModel], how: Averaging = "mean") -> ComplianceModel:
    """The model with the mean (seed 004's averaging) or median zero offsets and compliances."""
    if not models:
        raise ValueError("no models to average")
    if how not in ("mean", "median"):
        raise ValueError(f"averaging must be 'mean' or 'median', got {how!r}")
    first = models[0]
    avg = np.mean if how == "mean" else np.median
    return ComplianceModel(
        first.robot,
        avg([m.zero_offset_rad for m in models], axis=0),
        avg([m.compliance_rad_per_nm for m in models], axis=0),
        first.world_T_base,
        first.params.tool_xyz_mm,
        first.registration,
    )


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
    noise: NoiseKind = "uniform",
    noise_block: int = 1,
    payload_kg: float = 0.0,
    max_rounds: int = 20,
) -> PsdPoses:
    """Poses of the true robot whose laser line passes through the PSD centre (seed 004 §3).

    Before each pose the true robot's a5 and d5 get a fresh random error ``link5_noise_mm·U(0, 1)``
    (the paper's noise source; ``noise="centred"``: ``link5_noise_mm·(U(0, 1) − 0.5)``;
    ``noise_block = k > 1``: one draw shared by each run of k consecutive poses, as if the error
    were renewed once per calibration of k poses). The beam direction is drawn within
    ``setup.cone_deg`` of the PSD's inward normal, the roll about it uniformly, the stand-off in
    ``setup.standoff_mm``. The true joints sit at ``q + C·τ(q)`` of the commanded ``q``, as in
    :mod:`comp_daemon.models.effects`.
    """
    if noise not in ("uniform", "centred"):
        raise ValueError(f"noise must be 'uniform' or 'centred', got {noise!r}")
    if noise_block < 1:
        raise ValueError(f"noise_block must be >= 1, got {noise_block}")
    comp = finite_array(true_compliance_rad_per_nm, (N_JOINTS,), "true_compliance_rad_per_nm")
    centre = 0.5 if noise == "centred" else 0.0
    aim = _PsdAim(robot, true_params, comp, setup, payload_kg, max_rounds)
    if noise_block == 1:
        return aim.poses(n, rng, lambda m: link5_noise_mm * (rng.random((m, 2)) - centre))
    parts = []
    for start in range(0, n, noise_block):
        shared = link5_noise_mm * (rng.random(2) - centre)

        def same(m: int, d: NDArray[np.float64] = shared) -> NDArray[np.float64]:
            return np.repeat(d[None, :], m, axis=0)

        parts.append(aim.poses(min(noise_block, n - start), rng, same))
    return PsdPoses(
        a_deg=np.concatenate([p.a_deg for p in parts]),
        link5_delta_mm=np.concatenate([p.link5_delta_mm for p in parts]),
    )


class _PsdAim:
    """Aims the true robot's beam at the PSD centre from random directions (:func:`simulate_psd_poses`)."""

    def __init__(
        self,
        robot: RobotDescription,
        true_params: KinematicParams,
        comp: NDArray[np.float64],
        setup: PsdSetup,
        payload_kg: float,
        max_rounds: int,
    ) -> None:
        self.robot = robot
        self.true_params = true_params
        self.comp = comp
        self.setup = setup
        self.payload_kg = payload_kg
        self.max_rounds = max_rounds
        self.mass = MassModel.from_robot(robot)
        self.lim = np.sort(np.deg2rad(robot.axis_limits_deg) * robot.sign[:, None], axis=1)
        self.ik_params = KinematicParams(
            theta_offset_rad=true_params.theta_offset_rad,
            d_mm=true_params.d_mm,
            a_mm=true_params.a_mm,
            alpha_rad=true_params.alpha_rad,
            beta_rad=true_params.beta_rad,
            sign=true_params.sign,
            tool_xyz_mm=setup.mount.origin_mm,
            world_T_base=true_params.world_T_base,
        )
        self.seed_q = axes_deg_to_q_rad(np.asarray(setup.seed_deg, dtype=float), robot.sign)

    def poses(
        self, n: int, rng: np.random.Generator, draw_delta: Callable[[int], NDArray[np.float64]]
    ) -> PsdPoses:
        """``n`` reachable poses, the link-5 error of ``m`` candidates from ``draw_delta(m)``."""
        setup, robot, mount = self.setup, self.robot, self.setup.mount
        nrm = setup.normal / np.linalg.norm(setup.normal)
        found_a: list[NDArray[np.float64]] = []
        found_d: list[NDArray[np.float64]] = []
        have = 0
        for _ in range(self.max_rounds):
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
            delta = draw_delta(m)
            q = np.repeat(self.seed_q[None, :], m, axis=0)
            shift = np.zeros((m, 3))
            ok = np.ones(m, dtype=bool)
            for _k in range(4):  # the beam origin moves with the link-5 error: aim so that it lands
                res = solve_ik(
                    self.ik_params, self.lim, target_o - shift, r_f, q, tol_mm=1e-10, tol_rad=1e-13
                )
                q, ok = res.q_rad, res.ok
                shift = _link5_shift(self.ik_params, q, delta)
            a_cmd = q_rad_to_axes_deg(self._commanded(q), robot.sign)
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

    def _commanded(self, q_act: NDArray[np.float64]) -> NDArray[np.float64]:
        """Commanded q with ``q_cmd + C·τ(q_cmd) = q_act`` (fixed-point iteration)."""
        q_cmd = q_act.copy()
        for _k in range(30):
            tau = gravity_torques_nm(
                self.true_params, q_cmd, self.mass.link_mass_kg, self.mass.link_com_mm, self.payload_kg
            )
            q_next = q_act - self.comp * tau
            done = np.max(np.abs(q_next - q_cmd)) < 1e-15
            q_cmd = q_next
            if done:
                break
        return q_cmd


@dataclass(frozen=True, slots=True)
class Seed004Result:
    """Mean distance errors (mm) on the validation poses, seed 004's simulation and ours."""

    n_fit: int
    n_check: int
    poses_per_calibration: int
    uncompensated_mm: float
    true_model_mm: float  # the simulated robot's own offsets and compliance: the noise floor
    zero_offset_mm: float  # the original model, averaged over the calibrations (the paper's way)
    compliance_mm: float  # the improved model, averaged likewise
    zero_offset_joint_mm: float  # one calibration on all fit poses (not in the paper)
    compliance_joint_mm: float
    zero_offset_model: ComplianceModel
    compliance_model: ComplianceModel
    compliance_joint_model: ComplianceModel  # the improved model from one calibration on all fit poses
    calibration_sd: dict[str, float]  # SD of the improved model's parameters over the calibrations
    torque_range_nm: dict[str, tuple[float, float]]  # τ2, τ3 of the true robot over all poses
    true_offsets_rad: NDArray[np.float64]
    true_compliance_rad_per_nm: NDArray[np.float64]

    def table(self) -> dict[str, Any]:
        deg = np.rad2deg
        return {
            "rows": {"fit": self.n_fit, "check": self.n_check},
            "poses_per_calibration": self.poses_per_calibration,
            "mean_distance_error_mm": {
                "uncompensated": round(self.uncompensated_mm, 4),
                "true_model": round(self.true_model_mm, 4),
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
            "improved_calibrations_sd": {k: float(f"{v:.3g}") for k, v in self.calibration_sd.items()},
            "torque_range_nm": {
                k: [round(lo, 2), round(hi, 2)] for k, (lo, hi) in self.torque_range_nm.items()
            },
            "compliance_model_all_poses": {
                "zero_offset_deg": deg(self.compliance_joint_model.zero_offset_rad).round(4).tolist(),
                "C2_C3_rad_per_nm": self.compliance_joint_model.compliance_rad_per_nm[1:3].tolist(),
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
    noise: NoiseKind = "uniform",
    noise_block: int = 1,
    setup: PsdSetup | None = None,
    zero_offsets_deg: Sequence[float] = SEED004_ZERO_OFFSETS_DEG,
    compliance_rad_per_nm: Sequence[float] = SEED004_COMPLIANCE_RAD_PER_NM,
    compliance_joints: Sequence[int] = COMPLIANCE_JOINTS,
    payload_kg: float = 0.0,
    averaging: Averaging = "mean",
    known_point: bool = False,
    error: ErrorKind = "plane",
) -> Seed004Result:
    """Seed 004's simulation: 420 point-constraint poses of an IRB 120 with zero-offset errors
    (0, −1, −2, −1, 1, −2)°, compliance C2, C3 and link-5 noise; 210 calibrate (7 at a time, the
    results averaged), 210 validate by the PSD distance error.

    The defaults are the paper's; the other values are controlled departures from it: ``noise``
    and ``noise_block`` (:func:`simulate_psd_poses`), ``compliance_joints`` of the improved model,
    ``payload_kg`` at the TCP in every pose, ``averaging`` of the 7-pose results, ``known_point``
    (the PSD centre given to the calibration instead of identified) and ``error`` (``"line"``: the
    perpendicular distance of the PSD centre from the model's beam, :func:`line_distance_errors_mm`).
    """
    robot = robot if robot is not None else load_robot("irb120")
    setup = setup if setup is not None else PsdSetup()
    if not 0 < n_fit < n_poses:
        raise ValueError(f"need 0 < n_fit < n_poses, got {n_fit}, {n_poses}")
    if poses_per_calibration < 4 or n_fit % poses_per_calibration:
        raise ValueError(f"n_fit ({n_fit}) must be a multiple of poses_per_calibration (>= 4)")
    rng = np.random.default_rng(seed)
    offsets = np.deg2rad(np.asarray(zero_offsets_deg, dtype=float))
    comp_true = finite_array(compliance_rad_per_nm, (N_JOINTS,), "compliance_rad_per_nm")
    dx = np.zeros(N_PARAMS)
    dx[0:30:5] = offsets
    true_params = KinematicParams.from_robot(robot).apply(dx)
    if error not in ("plane", "line"):
        raise ValueError(f"error must be 'plane' or 'line', got {error!r}")
    poses = simulate_psd_poses(
        robot,
        true_params,
        comp_true,
        setup,
        n_poses,
        rng,
        link5_noise_mm=link5_noise_mm,
        noise=noise,
        noise_block=noise_block,
        payload_kg=payload_kg,
    )
    a_fit, a_chk = poses.a_deg[:n_fit], poses.a_deg[n_fit:]
    mass = MassModel.from_robot(robot)
    tau = gravity_torques_nm(
        true_params,
        axes_deg_to_q_rad(poses.a_deg, robot.sign),
        mass.link_mass_kg,
        mass.link_com_mm,
        payload_kg,
    )
    point = setup.center_mm if known_point else None

    def evaluate(model: ComplianceModel) -> float:
        if error == "line":
            err = line_distance_errors_mm(model, a_chk, setup.mount, setup.center_mm, payload_kg)
        else:
            err = psd_distance_errors_mm(model, a_chk, setup.mount, setup.center_mm, setup.normal, payload_kg)
        return float(err.mean())

    def calibrate(a: NDArray[np.float64], joints: Sequence[int]) -> ComplianceModel:
        return calibrate_point_constraint(
            robot, a, setup.mount, payload_kg=payload_kg, compliance_joints=joints, point_mm=point
        ).model

    groups = a_fit.reshape(-1, poses_per_calibration, 6)
    zero = average_models([calibrate(g, ()) for g in groups], averaging)
    comp_models = [calibrate(g, compliance_joints) for g in groups]
    comp = average_models(comp_models, averaging)
    c_all = np.array([m.compliance_rad_per_nm for m in comp_models])
    th_all = np.rad2deg([m.zero_offset_rad for m in comp_models])
    scatter = {f"C{j}_rad_per_nm": float(c_all[:, j - 1].std()) for j in (2, 3)}
    scatter |= {f"theta{j}_deg": float(th_all[:, j - 1].std()) for j in (2, 3)}
    zero_all = calibrate(a_fit, ())
    comp_all = calibrate(a_fit, compliance_joints)
    nominal = ComplianceModel(robot, np.zeros(N_JOINTS), np.zeros(N_JOINTS))
    return Seed004Result(
        n_fit=n_fit,
        n_check=n_poses - n_fit,
        poses_per_calibration=poses_per_calibration,
        uncompensated_mm=evaluate(nominal),
        true_model_mm=evaluate(ComplianceModel(robot, offsets, comp_true)),
        zero_offset_mm=evaluate(zero),
        compliance_mm=evaluate(comp),
        zero_offset_joint_mm=evaluate(zero_all),
        compliance_joint_mm=evaluate(comp_all),
        zero_offset_model=zero,
        compliance_model=comp,
        compliance_joint_model=comp_all,
        calibration_sd=scatter,
        torque_range_nm={f"tau{j}": (float(tau[:, j - 1].min()), float(tau[:, j - 1].max())) for j in (2, 3)},
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
    """``python -m benchmarks.seed004_compliance``: seed 004's simulation (and the tracker variant).

    The defaults are the paper's set-up; each option departs from it in one assumption (see
    :func:`reproduce_seed004`; :mod:`benchmarks.seed004_variations` tabulates them over seeds).
    """
    parser = argparse.ArgumentParser(description="Reproduce seed 004's zero-offset calibration simulation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--noise-mm",
        type=float,
        nargs="+",
        default=[0.1, 0.3, 1.0],
        help="scales s of the a5/d5 noise s·U(0,1) to run (mm)",
    )
    parser.add_argument("--poses", type=int, default=420)
    parser.add_argument("--fit", type=int, default=210)
    parser.add_argument("--per-calibration", type=int, default=7, help="poses per averaged calibration")
    parser.add_argument("--noise-kind", choices=["uniform", "centred"], default="uniform")
    parser.add_argument("--noise-block", type=int, default=1, help="consecutive poses sharing one noise draw")
    parser.add_argument("--averaging", choices=["mean", "median"], default="mean")
    parser.add_argument("--known-point", action="store_true", help="give the PSD centre to the calibration")
    parser.add_argument(
        "--error", choices=["plane", "line"], default="plane", help="distance-error definition"
    )
    parser.add_argument("--compliance-joints", type=int, nargs="*", default=list(COMPLIANCE_JOINTS))
    parser.add_argument("--compliance-scale", type=float, default=1.0, help="factor on the paper's C2, C3")
    parser.add_argument("--payload-kg", type=float, default=0.0)
    parser.add_argument("--cone-deg", type=float, default=PsdSetup().cone_deg)
    parser.add_argument("--standoff-mm", type=float, nargs=2, default=list(PsdSetup().standoff_mm))
    parser.add_argument("--no-tracker", action="store_true", help="skip the tracker variant")
    args = parser.parse_args(argv)
    setup = PsdSetup(cone_deg=args.cone_deg, standoff_mm=(args.standoff_mm[0], args.standoff_mm[1]))
    comp = tuple(args.compliance_scale * c for c in SEED004_COMPLIANCE_RAD_PER_NM)
    out: dict[str, Any] = {"psd": {}}
    for noise in args.noise_mm:
        result = reproduce_seed004(
            seed=args.seed,
            link5_noise_mm=noise,
            n_poses=args.poses,
            n_fit=args.fit,
            poses_per_calibration=args.per_calibration,
            noise=args.noise_kind,
            noise_block=args.noise_block,
            setup=setup,
            compliance_rad_per_nm=comp,
            compliance_joints=args.compliance_joints,
            payload_kg=args.payload_kg,
            averaging=args.averaging,
            known_point=args.known_point,
            error=args.error,
        )
        out["psd"][f"noise_{noise:g}_mm"] = result.table()
    if not args.no_tracker:
        out["tracker"] = reproduce_seed004_tracker(seed=args.seed, n_poses=args.poses, n_fit=args.fit).table()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
