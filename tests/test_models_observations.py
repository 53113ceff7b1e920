"""Tracker stations and a 6-DOF probe's orientation in the kinematic calibration."""

from __future__ import annotations

import numpy as np

from comp_daemon.kinematics.forward import flange_pose, tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import matrix_to_quat, quat_to_matrix, rotvec_to_matrix
from comp_daemon.models.effects import EffectParams
from comp_daemon.models.kinematic import KinematicProblem, calibrate_kinematic
from comp_daemon.models.observations import (
    FrameObservations,
    ObservedProblem,
)
from comp_daemon.robot.description import RobotDescription, load_robot

SIZES = np.tile([1e-3, 0.5, 0.5, 1e-3, 1e-3], 6)


def _axes(robot: RobotDescription, n: int, seed: int) -> np.ndarray:
    lim = robot.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.8, 0.8, (n, 6)) * np.minimum(half, 120.0)


def _rigid(rotvec: list[float], t: list[float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotvec_to_matrix(np.array(rotvec))
    out[:3, 3] = t
    return out


def _campaign(n: int = 120, seed: int = 3, noise_mm: float = 0.0, noise_deg: float = 0.0):
    """A robot with MDH errors measured from two stations (B: the frame of A turned by 50° and moved
    5 m) with a probe mounted turned on the flange; returns what a fit gets and the truth."""
    robot = load_robot("kr210")
    rng = np.random.default_rng(seed)
    dx = np.zeros(N_PARAMS)
    dx[:30] = rng.normal(size=30) * SIZES
    truth = KinematicParams.from_robot(robot).apply(dx)
    a = _axes(robot, n, seed)
    q = axes_deg_to_q_rad(a, truth.sign)
    p = tcp_position_mm(truth, q)
    mount = rotvec_to_matrix(np.array([0.3, -0.2, 1.1]))
    r = flange_pose(truth, q)[:, :3, :3] @ mount
    station = (np.arange(n) >= n // 2).astype(np.intp)
    frames = [
        _rigid([0.02, 0.01, 0.3], [2500.0, -800.0, 400.0]),
        _rigid([0.1, -0.05, np.radians(50)], [5000.0, 1000.0, 300.0]),
    ]
    p_meas, r_meas = np.empty_like(p), np.empty_like(r)
    for s, f in enumerate(frames):
        rows = station == s
        p_meas[rows] = p[rows] @ f[:3, :3].T + f[:3, 3]
        r_meas[rows] = f[:3, :3] @ r[rows]
    p_meas += rng.normal(size=p.shape) * noise_mm
    r_meas = rotvec_to_matrix(rng.normal(size=(n, 3)) * np.radians(noise_deg)) @ r_meas
    return robot, a, p_meas, r_meas, station, frames, truth


def _one_frame(a, p_meas, r_meas, station, frames, robot):
    """Station B's rows mapped into A's frame by a registration that is off by a little (what the
    preparation's first registration leaves to the fit)."""
    off = _rigid([0.002, -0.001, 0.003], [1.5, -2.0, 0.7])
    b_to_a = off @ frames[0] @ np.linalg.inv(frames[1])
    p, r = p_meas.copy(), r_meas.copy()
    rows = station == 1
    p[rows] = p[rows] @ b_to_a[:3, :3].T + b_to_a[:3, 3]
    r[rows] = b_to_a[:3, :3] @ r[rows]
    return p, r


def test_observed_problem_jacobian_matches_central_differences() -> None:
    robot, a, p_meas, r_meas, station, frames, _ = _campaign(n=30)
    p, r = _one_frame(a, p_meas, r_meas, station, frames, robot)
    start = KinematicParams.from_robot(robot).with_base(frames[0])
    inner = KinematicProblem(
        robot,
        start,
        EffectParams.zeros(),
        np.arange(N_PARAMS),
        [],
        a,
        p,
        None,
        0.0,
        None,
        row_weights=np.linspace(0.5, 1.5, 30),
    )
    obs = FrameObservations.of(30, station, ["A", "B"], r, np.full(30, 0.02), 0.01)
    problem = ObservedProblem(inner, obs, None, rotvec_to_matrix(np.array([0.3, -0.2, 1.0])))
    x = np.random.default_rng(1).normal(size=problem.size) * 1e-3
    jac = problem.jacobian(x)
    h = 1e-6
    num = np.stack(
        [(problem.residual(x + h * e) - problem.residual(x - h * e)) / (2 * h) for e in np.eye(problem.size)],
        axis=1,
    )
    scale = np.maximum(np.abs(num).max(axis=0), 1e-9)
    assert np.max(np.abs(jac - num) / scale) < 1e-5


def test_stations_are_registered_jointly_and_recover_the_robot() -> None:
    robot, a, p_meas, r_meas, station, frames, _ = _campaign(noise_mm=0.01)
    p, _ = _one_frame(a, p_meas, r_meas, station, frames, robot)
    joint = calibrate_kinematic(robot, a, p, station=station, station_names=["A", "B"], frame="tracker")
    one = calibrate_kinematic(robot, a, p, frame="tracker")
    assert joint.rms_mm < 0.03  # the noise (√3·0.01 = 0.017 mm)
    assert one.rms_mm > 0.3  # one frame for both stations: the registration's error stays
    assert "station_B_x" in joint.identified
    moved = joint.stations["B"]
    # station B's rows moved back by the registration's error
    off = _rigid([0.002, -0.001, 0.003], [1.5, -2.0, 0.7])
    assert np.allclose(moved[:3, :3], np.linalg.inv(off)[:3, :3], atol=2e-5)


def test_probe_orientation_is_fitted_with_its_mount_and_weighted_by_sigma() -> None:
    robot, a, p_meas, r_meas, station, _, _ = _campaign(noise_mm=0.02, noise_deg=0.01)
    rows = station == 0
    a0, p0, r0 = a[rows], p_meas[rows], r_meas[rows]
    fit = calibrate_kinematic(
        robot, a0, p0, probe_r=r0, sigma_mm=np.full(len(a0), 0.02), probe_sigma_deg=0.01
    )
    assert fit.orientation_rms_deg is not None and fit.orientation_rms_deg < 0.03
    assert fit.orientation_weight is not None
    assert np.isclose(fit.orientation_weight, 0.02 / (np.radians(0.01) * np.sqrt(2)))
    assert {"probe_rx", "probe_ry", "probe_rz"} & set(fit.identified)


def test_quaternions_round_trip() -> None:
    r = rotvec_to_matrix(np.random.default_rng(0).normal(size=(20, 3)))
    assert np.allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)
