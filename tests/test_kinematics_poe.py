"""POE kinematics (seed 002, A.1–A.2): equal to MDH at nominal, batch = single, Jacobian vs differences."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.kinematics.forward import flange_pose, tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.poe import (
    POE_PARAM_NAMES,
    PoeModel,
    irb120_table1,
    poe_error_jacobian,
    poe_flange_pose,
    poe_ik,
    poe_tcp_position_mm,
)
from comp_daemon.models.base import as_axes
from comp_daemon.robot.description import load_robot


def _random_axes(robot_name: str, n: int, seed: int) -> np.ndarray:
    lim = load_robot(robot_name).axis_limits_deg
    return np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], (n, 6))


@pytest.mark.parametrize("robot_name", ["kr210", "irb120", "mh6"])
def test_poe_equals_mdh_at_nominal(robot_name: str) -> None:
    robot = load_robot(robot_name)
    model = PoeModel.from_robot(robot)
    params = KinematicParams.from_robot(robot)
    a_deg = _random_axes(robot_name, 10_000, seed=1)
    q_rad = axes_deg_to_q_rad(a_deg, robot.sign)
    assert np.abs(poe_tcp_position_mm(model, a_deg) - tcp_position_mm(params, q_rad)).max() <= 1e-9
    r_poe = poe_flange_pose(model, a_deg)[:, :3, :3]
    r_mdh = flange_pose(params, q_rad)[:, :3, :3]
    assert np.abs(r_poe - r_mdh).max() <= 1e-12


def test_irb120_table1_twists_equal_mdh() -> None:
    robot = load_robot("irb120")
    model = irb120_table1(robot)
    np.testing.assert_allclose(model.base_R_flange0, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    pts = model.points_mm(np.zeros((1, 6)))[0]
    np.testing.assert_allclose(pts[:6], model.point_mm, atol=1e-12)  # segments rebuild Table 1's points
    np.testing.assert_allclose(pts[6], [374.0, 0.0, 630.0], atol=1e-12)
    a_deg = _random_axes("irb120", 10_000, seed=2)
    q_rad = axes_deg_to_q_rad(a_deg, robot.sign)
    params = KinematicParams.from_robot(robot)
    assert np.abs(poe_tcp_position_mm(model, a_deg) - tcp_position_mm(params, q_rad)).max() <= 1e-9
    assert (
        np.abs(poe_flange_pose(model, a_deg)[:, :3, :3] - flange_pose(params, q_rad)[:, :3, :3]).max()
        <= 1e-12
    )


def test_irb120_table1_refuses_another_robot() -> None:
    with pytest.raises(ValueError, match="IRB 120"):
        irb120_table1(load_robot("kr210"))


def test_batch_equals_single_pose() -> None:
    model = irb120_table1(load_robot("irb120")).with_tool((30.0, 20.0, 50.0))
    a_deg = _random_axes("irb120", 20, seed=3)
    x = np.random.default_rng(4).normal(0.0, [0.3] * 6 + [0.003] * 6)
    batch = poe_tcp_position_mm(model, a_deg, x)
    single = np.vstack([poe_tcp_position_mm(model, a_deg[k], x) for k in range(20)])
    assert np.abs(batch - single).max() <= 1e-12
    per_pose = poe_tcp_position_mm(model, a_deg, np.tile(x, (20, 1)))
    assert np.abs(batch - per_pose).max() <= 1e-12


def test_poses_not_of_six_axes_are_refused_naming_the_shape_given() -> None:
    robot = load_robot("irb120")
    model = irb120_table1(robot)
    params = KinematicParams.from_robot(robot)
    with pytest.raises(ValueError, match=r"axis values must have shape \(n, 6\), got \(5,\)"):
        poe_tcp_position_mm(model, np.zeros(5))
    with pytest.raises(ValueError, match=r"joint angles must have shape \(n, 6\), got \(5,\)"):
        tcp_position_mm(params, np.zeros(5))
    with pytest.raises(ValueError, match=r"axis values must have shape \(n, 6\), got \(2, 3, 6\)"):
        as_axes(np.zeros((2, 3, 6)))
    assert as_axes(np.arange(6.0)).shape == (1, 6)


@pytest.mark.parametrize("layout", ["table1", "from_robot"])
def test_error_jacobian_matches_central_differences(layout: str) -> None:
    robot = load_robot("irb120")
    base = irb120_table1(robot) if layout == "table1" else PoeModel.from_robot(robot)
    model = base.with_tool((30.0, 20.0, 50.0))
    a_deg = _random_axes("irb120", 15, seed=5)
    x0 = np.random.default_rng(6).normal(0.0, [0.5] * 6 + [0.01] * 6)
    jac = poe_error_jacobian(model, a_deg, x0)
    num = np.empty_like(jac)
    for k in range(12):
        h = 1e-4 if k < 6 else 1e-6
        e = np.zeros(12)
        e[k] = h
        num[:, :, k] = (
            poe_tcp_position_mm(model, a_deg, x0 + e) - poe_tcp_position_mm(model, a_deg, x0 - e)
        ) / (2 * h)
    scale = np.abs(num).max(axis=(0, 1))
    assert np.all(np.abs(jac - num).max(axis=(0, 1)) <= 1e-6 * np.maximum(scale, 1.0))


def test_dependent_length_columns_are_identical() -> None:
    model = irb120_table1(load_robot("irb120"))
    jac = poe_error_jacobian(model, _random_axes("irb120", 60, seed=7)).reshape(-1, 12)
    idx = {n: i for i, n in enumerate(POE_PARAM_NAMES)}
    assert np.abs(jac[:, idx["dl1"]] - jac[:, idx["dl2"]]).max() <= 1e-9
    assert np.abs(jac[:, idx["dl5"]] - jac[:, idx["dl6"]]).max() <= 1e-9
    assert np.abs(jac[:, idx["dtheta6"]]).max() <= 1e-9  # TCP on axis 6
    assert np.abs(jac[:, idx["dl3"]] - jac[:, idx["dl2"]]).max() > 1.0


def test_length_error_moves_points_as_the_segment_table_says() -> None:
    model = irb120_table1(load_robot("irb120"))
    dl = np.array([[0.0, 0.0, 0.0, 0.0, 2.0, 0.0]])  # l5 along x moves q4 onwards
    pts = model.points_mm(dl)[0]
    np.testing.assert_allclose(pts[:3], model.point_mm[:3])
    np.testing.assert_allclose(pts[3:6] - model.point_mm[3:], [[2.0, 0, 0]] * 3)


def test_poe_ik_round_trip_with_errors() -> None:
    model = irb120_table1(load_robot("irb120")).with_tool((30.0, 20.0, 50.0))
    x = np.random.default_rng(8).normal(0.0, [0.3] * 6 + [0.003] * 6)
    a_true = _random_axes("irb120", 30, seed=9) * 0.5
    pose = poe_flange_pose(model, a_true, x)
    p = poe_tcp_position_mm(model, a_true, x)
    a_found, err = poe_ik(model, p, pose[:, :3, :3], a_true + 2.0, x)
    assert err.max() < 1e-9
    pose_found = poe_flange_pose(model, a_found, x)
    assert np.abs(pose_found[:, :3, :3] - pose[:, :3, :3]).max() < 1e-9
    assert np.abs(poe_tcp_position_mm(model, a_found, x) - p).max() < 1e-9
    regular = np.abs(np.sin(np.deg2rad(a_true[:, 4]))) > 0.2  # away from the wrist singularity
    np.testing.assert_allclose(a_found[regular], a_true[regular], atol=1e-7)
