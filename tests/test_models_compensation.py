"""Compensation by model + inverse kinematics, and seed 000's joint mapping onto joints 1–3."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.kinematics.forward import chain, position_jacobian_mm
from comp_daemon.kinematics.inverse import UnreachableTargetError
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import rotvec_to_matrix as rotation_from_rotvec
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.chebyshev import fit_chebyshev
from comp_daemon.models.compensation import (
    CompensationLimits,
    CompensationRefused,
    compensate,
    feed_forward,
    joint_mapping,
    nominal_solution,
    nominal_targets,
)
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import KinematicModel, calibrate_kinematic
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")


def _axes(n: int, seed: int) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 90.0)


def _tracker() -> np.ndarray:
    w = np.eye(4)
    w[:3, :3] = rotation_from_rotvec(np.array([0.02, 0.0, -0.9]))
    w[:3, 3] = [2500.0, 800.0, -600.0]
    return w


def _models() -> list[ErrorModel]:
    """A kinematic model with joint effects (tracker frame) and a Chebyshev model fitted on a robot."""
    rng = np.random.default_rng(1)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 5e-4)
    eff = EffectParams.zeros(1).with_values(["eps2", "eps3", "c2_1"], [2e-4, -3e-4, 0.01])
    kin = KinematicModel(KR, truth.with_base(_tracker() @ truth.world_T_base), eff, registration=_tracker())
    a = _axes(200, 2)
    cheb = fit_chebyshev(KR, a, twin_tcp_mm(KR, truth, eff, a), 3).model
    return [kin, cheb, NominalModel(KR, _tracker())]


@pytest.mark.parametrize("index", [0, 1, 2])
def test_predicted_position_of_the_compensated_command_is_the_target(index: int) -> None:
    model = _models()[index]
    a_nominal = _axes(25, 3)
    wanted, _ = nominal_targets(model, a_nominal)
    result = compensate(model, wanted, a_seed_deg=a_nominal)
    assert result.converged
    predicted = model.predict_tcp_mm(result.a_deg)
    wanted_world = wanted @ model.registration[:3, :3].T + model.registration[:3, 3]
    assert np.linalg.norm(predicted - wanted_world, axis=1).max() < 1e-6
    assert result.residual_mm.max() < 1e-6
    if index < 2:  # a real error model moves the commands
        assert np.abs(result.a_deg - result.a_uncompensated_deg).max() > 1e-3


def test_orientation_is_held_while_the_position_is_compensated() -> None:
    model = _models()[1]
    a_nominal = _axes(10, 4)
    wanted, rot = nominal_targets(model, a_nominal)
    result = compensate(model, wanted, rot, a_seed_deg=a_nominal)
    assert result.residual_mm.max() < 1e-6
    params = model.ik_params()
    frames = chain(params, axes_deg_to_q_rad(result.a_deg, params.sign)).world_T_frame[:, 6, :3, :3]
    np.testing.assert_allclose(frames, model.registration[:3, :3] @ rot, atol=1e-9)


def test_kinematic_model_with_effects_is_inverted_through_its_effects() -> None:
    """The IK runs on the calibrated geometry; the iteration removes what the joint effects add."""
    model = _models()[0]
    a_nominal = _axes(10, 5)
    wanted, _ = nominal_targets(model, a_nominal)
    result = compensate(model, wanted, a_seed_deg=a_nominal)
    assert result.iterations >= 2
    assert result.residual_mm.max() < 1e-6


def test_unreachable_targets_are_named() -> None:
    model = NominalModel(KR)
    wanted = np.array([[1800.0, 0.0, 1200.0], [9000.0, 0.0, 0.0]])
    with pytest.raises(UnreachableTargetError, match="target 2"):
        compensate(model, wanted, a_seed_deg=np.array([0.0, -90.0, 90.0, 0.0, 45.0, 0.0]))


def test_joint_mapping_solves_the_position_jacobian_of_joints_1_to_3() -> None:
    params = KinematicParams.from_robot(KR)
    a = _axes(12, 6)
    error = np.random.default_rng(7).normal(size=(12, 3)) * 0.3
    corr = joint_mapping(params, a, error)
    assert np.all(corr[:, 3:] == 0.0)
    q = axes_deg_to_q_rad(a, params.sign)
    jac = position_jacobian_mm(params, q)[:, :, :3]
    dq = axes_deg_to_q_rad(corr, params.sign)[:, :3]  # the correction in joint space (rad)
    # J·(−Δθ) = −ΔP: the corrected command moves the TCP back by the estimated error
    np.testing.assert_allclose(np.einsum("nij,nj->ni", jac, dq), -error, atol=1e-9)


def test_feed_forward_removes_the_estimated_error_to_first_order() -> None:
    model = _models()[1]
    a_nominal = _axes(60, 8)
    # away from the singularities of the 3×3 position Jacobian of joints 1–3 (TCP near axis 1, …)
    params = model.ik_params()
    jac = position_jacobian_mm(params, axes_deg_to_q_rad(a_nominal, params.sign))[:, :, :3]
    a_nominal = a_nominal[np.linalg.cond(jac) < 50.0]
    assert len(a_nominal) > 20
    ff = feed_forward(model, a_nominal)
    wanted, _ = nominal_targets(model, a_nominal)
    before = np.linalg.norm(ff.estimated_error_mm, axis=1)
    after = np.linalg.norm(model.predict_tcp_mm(ff.a_deg) - wanted, axis=1)
    assert before.max() > 0.1
    assert after.max() < 0.05 * before.max()
    assert np.all(ff.correction_deg[:, 3:] == 0.0)


def test_calibrated_model_compensates_the_true_robot_to_the_noise_level() -> None:
    rng = np.random.default_rng(9)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 5e-4)
    a = _axes(150, 10)
    measured = twin_tcp_mm(KR, truth, EffectParams.zeros(), a) + rng.normal(size=(150, 3)) * 0.01
    model = calibrate_kinematic(KR, a, measured).model
    a_nominal = _axes(20, 11)
    wanted, _ = nominal_targets(model, a_nominal)
    result = compensate(model, wanted, a_seed_deg=a_nominal)
    reached = twin_tcp_mm(KR, truth, EffectParams.zeros(), result.a_deg)
    before = twin_tcp_mm(KR, truth, EffectParams.zeros(), a_nominal)
    assert np.linalg.norm(before - wanted, axis=1).max() > 0.5
    assert np.linalg.norm(reached - wanted, axis=1).max() < 0.03


def _well_conditioned(model: ErrorModel, a: np.ndarray) -> np.ndarray:
    """The rows of ``a`` away from the singularities of the position Jacobian of joints 1–3 and of
    the wrist."""
    params = model.ik_params()
    jac = position_jacobian_mm(params, axes_deg_to_q_rad(a, params.sign))[:, :, :3]
    return a[(np.linalg.cond(jac) < 50.0) & (np.abs(a[:, 4]) > 10.0)]


@pytest.mark.parametrize("index", [0, 1, 2])
def test_seed000_mapping_moves_only_joints_1_to_3_onto_the_target(index: int) -> None:
    model = _models()[index]
    a_nominal = _well_conditioned(model, _axes(40, 12))
    assert len(a_nominal) > 10
    wanted, rot = nominal_targets(model, a_nominal)
    wide = CompensationLimits(max_axis_change_deg=2.0)  # the test models' errors reach 3.4 mm
    result = compensate(model, wanted, rot, a_seed_deg=a_nominal, mapping="three-axis", limits=wide)
    assert result.converged and result.residual_mm.max() < 1e-6
    wanted_world = wanted @ model.registration[:3, :3].T + model.registration[:3, 3]
    assert np.linalg.norm(model.predict_tcp_mm(result.a_deg) - wanted_world, axis=1).max() < 1e-6
    np.testing.assert_array_equal(result.a_deg[:, 3:], result.a_uncompensated_deg[:, 3:])  # the wrist
    if index < 2:
        assert np.abs(result.da_deg[:, :3]).max() > 1e-3
        # the six-axis mapping reaches the same predicted TCP with other axis values
        six = compensate(model, wanted, rot, a_seed_deg=a_nominal, limits=wide)
        np.testing.assert_allclose(six.predicted_mm, result.predicted_mm, atol=1e-6)
        assert np.abs(six.a_deg - result.a_deg).max() > 1e-4


def test_first_step_of_the_seed000_mapping_is_the_papers_feed_forward() -> None:
    model = _models()[1]
    a_nominal = _well_conditioned(model, _axes(40, 12))
    wanted, _ = nominal_targets(model, a_nominal)
    wide = CompensationLimits(max_axis_change_deg=2.0)
    one = compensate(model, wanted, a_seed_deg=a_nominal, mapping="three-axis", max_iter=1, limits=wide)
    np.testing.assert_allclose(one.a_deg, feed_forward(model, a_nominal).a_deg, atol=1e-12)
    assert not one.converged  # one step leaves the second-order remainder
    full = compensate(model, wanted, a_seed_deg=a_nominal, mapping="three-axis", limits=wide)
    assert full.residual_mm.max() < 1e-6 < one.residual_mm.max()


def test_the_limits_apply_to_the_seed000_mapping() -> None:
    model = _models()[1]
    a_nominal = _well_conditioned(model, _axes(20, 14))
    wanted, _ = nominal_targets(model, a_nominal)
    wide = CompensationLimits(max_axis_change_deg=2.0)
    free = compensate(model, wanted, a_seed_deg=a_nominal, mapping="three-axis", limits=wide)
    worst = float(np.abs(free.da_deg).max())
    tight = CompensationLimits(max_axis_change_deg=0.5 * worst)
    with pytest.raises(CompensationRefused, match="would change by") as caught:
        compensate(model, wanted, a_seed_deg=a_nominal, mapping="three-axis", limits=tight)
    assert all(r.axis in (1, 2, 3) for r in caught.value.refusals)
    # the validity region of the Chebyshev model: a target beyond its sampled A1 range is refused
    beyond = a_nominal[:1].copy()
    beyond[0, 0] = model.range_deg[0][1] + 30.0  # type: ignore[attr-defined]
    p, r = nominal_targets(model, beyond)
    with pytest.raises(CompensationRefused, match="validity region"):
        compensate(model, p, r, a_seed_deg=beyond, mapping="three-axis")


def test_an_unknown_mapping_is_an_error() -> None:
    model = NominalModel(KR)
    with pytest.raises(ValueError, match="six-axis, three-axis"):
        compensate(model, np.array([[1800.0, 0.0, 1200.0]]), mapping="paper")  # type: ignore[arg-type]


def test_targets_not_of_three_coordinates_are_refused_naming_the_shape() -> None:
    with pytest.raises(ValueError, match=r"target positions must have shape \(n, 3\), got \(4, 2\)"):
        compensate(NominalModel(KR), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"target positions must have shape \(n, 3\), got \(2, 4, 3\)"):
        nominal_solution(KR, np.zeros((2, 4, 3)))
