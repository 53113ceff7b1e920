"""Compensation by model + inverse kinematics, and seed 000's joint mapping onto joints 1–3."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.kinematics.forward import chain, position_jacobian_mm
from comp_daemon.kinematics.inverse import UnreachableTargetError
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import rotvec_to_matrix as rotation_from_rotvec
from comp_daemon.models.base import ErrorModel, NominalModel
from comp_daemon.models.chebyshev import fit_chebyshev
from comp_daemon.models.compensation import compensate, feed_forward, joint_mapping, nominal_targets
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import KinematicModel, calibrate_kinematic
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
