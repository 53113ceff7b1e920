"""Kinematic (MDH) calibration: exact recovery, the noise floor, tracker frames, seed 001's joint terms."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.estimation.identifiability import analyze_identifiability, mdh_priority
from comp_daemon.kinematics.forward import identification_jacobian, tcp_position_mm
from comp_daemon.kinematics.params import (
    N_PARAMS,
    PARAM_NAMES,
    KinematicParams,
    axes_deg_to_q_rad,
)
from comp_daemon.kinematics.so3 import left_jacobian as so3_left_jacobian
from comp_daemon.kinematics.so3 import rotvec_to_matrix as rotation_from_rotvec
from comp_daemon.models.effects import TRANSMISSION_EFFECTS, EffectParams, effect_param_names, twin_tcp_mm
from comp_daemon.models.kinematic import (
    KinematicProblem,
    _Layout,
    calibrate_kinematic,
    target_param_names,
)
from comp_daemon.models.observations import MOUNT_NAMES, station_param_names
from comp_daemon.robot.description import RobotDescription, load_robot

SIZES = np.tile([1e-3, 0.5, 0.5, 1e-3, 1e-3], 6)  # theta, d, a, alpha, beta per joint (rad, mm)


def _axes(robot: RobotDescription, n: int, seed: int) -> np.ndarray:
    lim = robot.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.8, 0.8, (n, 6)) * np.minimum(half, 120.0)


def _tracker_frame() -> np.ndarray:
    w = np.eye(4)
    w[:3, :3] = rotation_from_rotvec(np.array([0.05, -0.02, 0.6]))
    w[:3, 3] = [-3500.0, 1200.0, -850.0]
    return w


def _identifiable(robot: RobotDescription, a_deg: np.ndarray) -> np.ndarray:
    params = KinematicParams.from_robot(robot)
    jac = identification_jacobian(params, axes_deg_to_q_rad(a_deg, params.sign))
    return analyze_identifiability(jac, PARAM_NAMES, priority=mdh_priority(params)).identifiable_index


def _truth(robot: RobotDescription, dx: np.ndarray, world: np.ndarray | None) -> KinematicParams:
    p = KinematicParams.from_robot(robot).apply(dx)
    return p if world is None else p.with_base(world @ p.world_T_base)


def test_so3_left_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(0)
    for r in (rng.normal(size=3) * 0.7, np.array([1e-8, -2e-8, 3e-9])):
        v = rng.normal(size=3)
        # −[R v]× J_l: column k is the derivative w.r.t. r_k
        analytic = -_skew(rotation_from_rotvec(r) @ v) @ so3_left_jacobian(r)
        h = 1e-6
        num = np.stack(
            [
                (rotation_from_rotvec(r + h * e) @ v - rotation_from_rotvec(r - h * e) @ v) / (2 * h)
                for e in np.eye(3)
            ],
            axis=1,
        )
        np.testing.assert_allclose(analytic, num, atol=1e-8)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def test_calibration_jacobian_matches_central_differences() -> None:
    kr = load_robot("kr210")
    a = _axes(kr, 6, 1)
    dirs = np.random.default_rng(2).choice([-1.0, 1.0], size=a.shape)
    start = KinematicParams.from_robot(kr).with_base(_tracker_frame())
    names = effect_param_names(["ratio", "backlash"], (1, 2, 3))
    geo = np.arange(N_PARAMS)
    problem = KinematicProblem(
        kr, start, EffectParams.zeros(), geo, names, a, np.zeros((6, 3)), dirs, 0.0, None
    )
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(size=N_PARAMS) * np.r_[SIZES, 1.0, 1.0, 1.0, 0.3, -0.2, 0.4, 1, 1, 1],
                        rng.normal(size=len(names)) * 1e-3])  # fmt: skip
    jac = problem.jacobian(x)
    # steps: 1e-6 rad for angles, 1e-3 mm for lengths (rounding of ~3 m positions), effects by unit
    length = np.zeros(x.size, bool)
    length[[*range(1, 30, 5), *range(2, 30, 5), 30, 31, 32, 36, 37, 38]] = True
    h = np.where(length, 1e-3, 1e-6)
    h[N_PARAMS + 3 :] = 1e-4  # backlash (deg)
    num = np.empty_like(jac)
    for k in range(x.size):
        e = np.zeros_like(x)
        e[k] = h[k]
        num[:, k] = (problem.residual(x + e) - problem.residual(x - e)) / (2 * h[k])
    scale = np.abs(jac).max(axis=0)
    assert np.all(np.abs(jac - num) <= 1e-6 * scale + 1e-6)


@pytest.mark.parametrize(("name", "tracker"), [("kr210", True), ("mh6", False)])
def test_noise_free_parameters_are_recovered_to_1e_6_of_their_size(name: str, tracker: bool) -> None:
    robot = load_robot(name)
    a = _axes(robot, 120, 4)
    ident = _identifiable(robot, a)
    rng = np.random.default_rng(5)
    sizes = np.r_[SIZES, 1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3, 0.5, 0.5, 0.5]
    dx = np.zeros(N_PARAMS)
    dx[ident] = rng.normal(size=ident.size) * sizes[ident]
    truth = _truth(robot, dx, _tracker_frame() if tracker else None)
    p = tcp_position_mm(truth, axes_deg_to_q_rad(a, robot.sign))
    fit = calibrate_kinematic(robot, a, p)
    assert fit.frame == ("tracker" if tracker else "base")
    assert fit.lm.converged
    assert fit.rms_mm < 1e-9
    diff = fit.model.params.difference(truth)
    assert np.all(np.abs(diff[ident]) <= 1e-6 * np.abs(dx[ident]) + 1e-12)
    others = np.setdiff1d(np.arange(30), ident)
    assert np.all(diff[others] == 0.0)  # never moved: they stay at nominal (= truth)


def test_noise_floor_for_a_robot_with_only_geometric_errors() -> None:
    kr = load_robot("kr210")
    rng = np.random.default_rng(6)
    dx = rng.normal(size=N_PARAMS) * np.r_[SIZES, 1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3, 0.5, 0.5, 0.5]
    truth = _truth(kr, dx, _tracker_frame())  # every parameter off, identifiable or not
    a = _axes(kr, 500, 7)
    sigma = 0.02
    exact = tcp_position_mm(truth, axes_deg_to_q_rad(a, kr.sign))
    measured = exact + rng.normal(size=exact.shape) * sigma
    fit_rows, check_rows = np.arange(300), np.arange(300, 500)
    fit = calibrate_kinematic(kr, a[fit_rows], measured[fit_rows])
    assert fit.report.n_identifiable == 27
    pred = fit.model.predict_tcp_mm(a[check_rows])
    floor = sigma * np.sqrt(3.0)
    rms_vs_measured = np.sqrt(np.mean(np.sum((pred - measured[check_rows]) ** 2, axis=1)))
    rms_vs_truth = np.sqrt(np.mean(np.sum((pred - exact[check_rows]) ** 2, axis=1)))
    assert 0.9 * floor < rms_vs_measured < 1.1 * floor
    assert rms_vs_truth < 0.4 * floor  # the model error is well below the measurement noise
    assert fit.rms_mm == pytest.approx(floor * np.sqrt(1 - 27 / 900), rel=0.1)
    # standard errors are consistent with the scatter
    assert np.all(np.isfinite(fit.std)) and np.all(fit.std > 0)


def test_seed001_ratio_and_backlash_are_recovered() -> None:
    kr = load_robot("kr210")
    a = _axes(kr, 200, 8)
    rng = np.random.default_rng(9)
    dirs = rng.choice([-1.0, 1.0], size=a.shape)
    ident = _identifiable(kr, a)
    dx = np.zeros(N_PARAMS)
    dx[ident] = (
        rng.normal(size=ident.size) * np.r_[SIZES, 1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3, 0.5, 0.5, 0.5][ident]
    )
    truth = _truth(kr, dx, None)
    names = effect_param_names(list(TRANSMISSION_EFFECTS))
    values = np.r_[rng.normal(size=6) * 5e-5, np.abs(rng.normal(size=6)) * 5e-3]  # eps (1), h (deg)
    eff = EffectParams.zeros().with_values(names, values)
    p = twin_tcp_mm(kr, truth, eff, a, dirs)
    plain = calibrate_kinematic(kr, a, p)
    fit = calibrate_kinematic(kr, a, p, dir=dirs, effects=TRANSMISSION_EFFECTS)
    assert plain.rms_mm > 0.01  # geometry alone cannot explain direction-dependent errors
    assert fit.rms_mm < 1e-8
    assert fit.model.effects is not None
    got = fit.model.effects.get(names)
    np.testing.assert_allclose(got, values, rtol=1e-6)
    np.testing.assert_allclose(fit.model.predict_tcp_mm(a, dirs), p, atol=1e-8)


def test_backlash_without_directions_is_reported_unidentifiable() -> None:
    kr = load_robot("kr210")
    a = _axes(kr, 60, 10)
    p = tcp_position_mm(KinematicParams.from_robot(kr), axes_deg_to_q_rad(a, kr.sign))
    fit = calibrate_kinematic(kr, a, p, effects=["backlash"])
    assert set(fit.report.removed_names("zero")) == {f"h{j}" for j in range(1, 7)}
    assert not any(n.startswith("h") for n in fit.identified)


def test_bad_shapes_are_refused() -> None:
    kr = load_robot("kr210")
    with pytest.raises(ValueError, match=r"measured positions must have shape \(4, 3\)"):
        calibrate_kinematic(kr, np.zeros((4, 6)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="unknown effect"):
        calibrate_kinematic(kr, np.zeros((4, 6)), np.zeros((4, 3)), effects=["wobble"])


def test_gravity_compliance_is_identified_from_zero() -> None:
    """Compliance columns exist at zero compliance (the start), so C2, C3 are found with payloads."""
    kr = load_robot("kr210")
    a = _axes(kr, 150, 16)
    payload = np.where(np.arange(150) % 2 == 0, 0.0, 120.0)
    eff = EffectParams.zeros().with_values(["C2", "C3"], [2e-8, 3e-8])
    truth = _truth(kr, np.zeros(N_PARAMS), None)
    p = twin_tcp_mm(kr, truth, eff, a, None, payload)
    fit = calibrate_kinematic(kr, a, p, payload_kg=payload, effects=["compliance"], effect_joints=(2, 3))
    assert {"C2", "C3"} <= set(fit.identified)
    assert fit.model.effects is not None
    np.testing.assert_allclose(fit.model.effects.get(["C2", "C3"]), [2e-8, 3e-8], rtol=1e-6)


def test_parameter_layout_offers_stations_first_and_flange_points_after_the_tool() -> None:
    start = KinematicParams.from_robot(load_robot("kr210"))
    stations = station_param_names(["B"])
    layout = _Layout(("eps2",), tuple(target_param_names(1)), (*stations, *MOUNT_NAMES))
    order = layout.priority(start)
    assert sorted(order) == sorted(layout.names)
    tool_end = order.index("tool_z") + 1
    assert list(order[:6]) == stations  # a station's frame: nothing of the robot stands in for it
    assert order[6] == "base_x"
    assert list(order[tool_end : tool_end + 6]) == ["target2_x", "target2_y", "target2_z", *MOUNT_NAMES]
    assert not any(n.startswith("tool_") or n.startswith("base_") for n in order[tool_end:])
    assert "base_x" not in layout.candidates(fit_base=False, fit_tool=True)
    assert "tool_x" not in layout.candidates(fit_base=True, fit_tool=False)
    assert layout.candidates(fit_base=True, fit_tool=True) == list(layout.names)


def test_parameter_layout_splits_kept_columns_into_the_problems_blocks() -> None:
    layout = _Layout(("eps2", "h3"), tuple(target_param_names(2)), tuple(MOUNT_NAMES))
    names = layout.names
    kept = ["theta2", "tool_z", "h3", "target2_y", "target3_x", "probe_rz"]
    idx = np.array([names.index(n) for n in kept], dtype=np.intp)
    geo, effs, more, extra = layout.split(idx)
    assert [PARAM_NAMES[i] for i in geo] == ["theta2", "tool_z"]
    assert effs == ["h3"]
    assert more.tolist() == [1, 3]  # into the flattened (K − 1, 3) offsets: target2_y, target3_x
    assert extra.tolist() == [2]  # probe_rz
