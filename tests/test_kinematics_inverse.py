"""Inverse kinematics: FK → IK → FK round trips, limits, explicit failure for unreachable targets."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.kinematics.forward import chain, tcp_position_mm
from comp_daemon.kinematics.inverse import (
    UnreachableTargetError,
    require_reachable,
    solve_ik,
    solve_ik_axes,
)
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad, q_rad_to_axes_deg
from comp_daemon.robot.description import PRESETS, load_robot


def _random_axes(name: str, n: int, seed: int) -> np.ndarray:
    robot = load_robot(name)
    lim = robot.axis_limits_deg
    # stay a little inside the limits and away from the wrist singularity A5 = 0
    a = np.random.default_rng(seed).uniform(lim[:, 0] * 0.9, lim[:, 1] * 0.9, (n, 6))
    a[:, 4] = np.where(np.abs(a[:, 4]) < 5, 5 + a[:, 4], a[:, 4])
    return np.clip(a, lim[:, 0], lim[:, 1])


@pytest.mark.parametrize("name", list(PRESETS))
def test_fk_ik_fk_round_trip_full_pose(name: str) -> None:
    robot = load_robot(name)
    params = KinematicParams.from_robot(robot)
    a_true = _random_axes(name, 200, 1)
    q_true = axes_deg_to_q_rad(a_true, robot.sign)
    ch = chain(params, q_true)
    seed = q_true + np.random.default_rng(2).normal(0, 0.1, q_true.shape)
    res = solve_ik(params, robot.q_limits_rad, ch.tcp_mm, ch.world_T_frame[:, 6, :3, :3], seed)
    assert res.ok.all()
    q = require_reachable(res)
    back = chain(params, q)
    np.testing.assert_allclose(back.tcp_mm, ch.tcp_mm, atol=1e-5)
    np.testing.assert_allclose(back.world_T_frame[:, 6, :3, :3], ch.world_T_frame[:, 6, :3, :3], atol=1e-8)
    lim = robot.q_limits_rad
    assert np.all(q >= lim[:, 0] - 1e-12) and np.all(q <= lim[:, 1] + 1e-12)


def test_position_only_targets_stay_near_the_seed() -> None:
    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    a_true = _random_axes("kr210", 100, 3)
    target = tcp_position_mm(params, axes_deg_to_q_rad(a_true, robot.sign))
    seed = a_true + np.random.default_rng(4).normal(0, 2.0, a_true.shape)
    a_sol, res = solve_ik_axes(params, robot.sign, robot.axis_limits_deg, target, None, seed)
    assert res.ok.mean() > 0.97
    ok = res.ok
    np.testing.assert_allclose(
        tcp_position_mm(params, axes_deg_to_q_rad(a_sol[ok], robot.sign)), target[ok], atol=1e-5
    )
    # minimum-norm steps from a nearby seed: the answer is on the seed's branch, within a few degrees
    assert np.abs(a_sol[ok] - seed[ok]).max() < 20.0


def test_unreachable_target_is_an_explicit_failure() -> None:
    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    a_seed = np.array([[0.0, -90.0, 90.0, 0.0, 30.0, 0.0]])
    far = np.array([[5000.0, 0.0, 1000.0], [1500.0, 0.0, 1200.0]])
    _, res = solve_ik_axes(params, robot.sign, robot.axis_limits_deg, far, None, np.repeat(a_seed, 2, axis=0))
    assert not res.ok[0] and res.ok[1]
    with pytest.raises(UnreachableTargetError, match="target 1") as info:
        require_reachable(res)
    assert list(info.value.indices) == [0]
    assert info.value.position_error_mm[0] > 1000


def test_joint_limits_are_respected_even_when_the_target_needs_more() -> None:
    """A pose reachable only beyond A2's limit is refused, not reached by leaving the limits."""
    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    a = np.array([[0.0, -2.0, 90.0, 0.0, 30.0, 0.0]])  # A2 = -2 is beyond max_deg = -5
    target = tcp_position_mm(params, axes_deg_to_q_rad(a, robot.sign))
    seed = np.array([[0.0, -10.0, 90.0, 0.0, 30.0, 0.0]])
    a_sol, res = solve_ik_axes(
        params,
        robot.sign,
        robot.axis_limits_deg,
        target,
        abc_deg_to_matrix(np.zeros((1, 3)))
        @ chain(params, axes_deg_to_q_rad(a, robot.sign)).world_T_frame[:, 6, :3, :3],
        seed,
    )
    lim = robot.axis_limits_deg
    assert np.all(a_sol >= lim[:, 0] - 1e-9) and np.all(a_sol <= lim[:, 1] + 1e-9)
    assert not res.ok[0]


def test_axis_conversion_round_trip() -> None:
    robot = load_robot("kr210")
    a = _random_axes("kr210", 10, 9)
    np.testing.assert_allclose(q_rad_to_axes_deg(axes_deg_to_q_rad(a, robot.sign), robot.sign), a, atol=1e-12)
