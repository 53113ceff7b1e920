"""Every analytic Jacobian against central differences, and batch against single-pose evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.kinematics.forward import (
    chain,
    geometric_jacobian,
    identification_jacobian,
    position_jacobian_mm,
    tcp_position_mm,
)
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, joint_param_index
from comp_daemon.robot.description import PRESETS, load_robot


def _perturbed_params(name: str, seed: int) -> KinematicParams:
    """Nominal parameters moved off nominal (incl. beta and a base frame), so no term vanishes by symmetry."""
    rng = np.random.default_rng(seed)
    dx = np.zeros(N_PARAMS)
    dx[:30] = rng.normal(0, 1, 30) * np.tile([1e-2, 1.0, 1.0, 1e-2, 1e-2], 6)
    dx[30:33] = rng.normal(0, 500, 3)
    dx[33:36] = rng.normal(0, 0.3, 3)
    dx[36:39] = rng.normal(0, 5, 3)
    return KinematicParams.from_robot(load_robot(name)).apply(dx)


@pytest.mark.parametrize("name", list(PRESETS))
def test_identification_jacobian_matches_central_differences(name: str) -> None:
    params = _perturbed_params(name, 11)
    q = np.random.default_rng(5).uniform(-2.5, 2.5, (7, 6))
    jac = identification_jacobian(params, q)
    assert jac.shape == (7, 3, N_PARAMS)
    h = 1e-6
    for k in range(N_PARAMS):
        dx = np.zeros(N_PARAMS)
        dx[k] = h
        num = (tcp_position_mm(params.apply(dx), q) - tcp_position_mm(params.apply(-dx), q)) / (2 * h)
        scale = max(1.0, float(np.abs(num).max()))
        np.testing.assert_allclose(jac[:, :, k], num, atol=2e-6 * scale, err_msg=PARAM_NAMES[k])


@pytest.mark.parametrize("name", list(PRESETS))
def test_geometric_jacobian_matches_central_differences(name: str) -> None:
    params = _perturbed_params(name, 12)
    q = np.random.default_rng(6).uniform(-2.5, 2.5, (5, 6))
    jac = geometric_jacobian(params, q)
    h = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        plus, minus = chain(params, q + dq), chain(params, q - dq)
        dp = (plus.tcp_mm - minus.tcp_mm) / (2 * h)
        np.testing.assert_allclose(jac[:, :3, j], dp, atol=2e-5)
        # angular velocity: (dR/dq) Rᵀ is the skew matrix of the joint's axis
        r_dot = (plus.world_T_frame[:, 6, :3, :3] - minus.world_T_frame[:, 6, :3, :3]) / (2 * h)
        w = r_dot @ np.swapaxes(chain(params, q).world_T_frame[:, 6, :3, :3], 1, 2)
        omega = np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=1)
        np.testing.assert_allclose(jac[:, 3:, j], omega, atol=1e-8)
    np.testing.assert_array_equal(position_jacobian_mm(params, q), jac[:, :3])


@pytest.mark.parametrize("name", list(PRESETS))
def test_batch_agrees_with_single_pose(name: str) -> None:
    params = _perturbed_params(name, 13)
    q = np.random.default_rng(7).uniform(-3, 3, (20, 6))
    ch = chain(params, q)
    jac = identification_jacobian(params, q, ch)
    gj = geometric_jacobian(params, q, ch)
    for i in range(q.shape[0]):
        one = chain(params, q[i])
        np.testing.assert_array_equal(one.tcp_mm[0], ch.tcp_mm[i])
        np.testing.assert_array_equal(one.world_T_frame[0], ch.world_T_frame[i])
        np.testing.assert_allclose(identification_jacobian(params, q[i])[0], jac[i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(geometric_jacobian(params, q[i])[0], gj[i], rtol=0, atol=1e-12)


def test_parameter_vector_layout_and_apply_difference_round_trip() -> None:
    assert PARAM_NAMES[joint_param_index("beta", 2)] == "beta2"
    assert PARAM_NAMES[joint_param_index("theta", 1)] == "theta1"
    assert len(set(PARAM_NAMES)) == N_PARAMS == 39
    nominal = KinematicParams.from_robot(load_robot("kr210"))
    moved = _perturbed_params("kr210", 14)
    dx = moved.difference(nominal)
    again = nominal.apply(dx)
    np.testing.assert_allclose(again.joint_table(), moved.joint_table(), atol=1e-12)
    np.testing.assert_allclose(again.world_T_base, moved.world_T_base, atol=1e-9)
    np.testing.assert_allclose(again.tool_xyz_mm, moved.tool_xyz_mm, atol=1e-12)


def test_joint_table_round_trips_and_is_copied() -> None:
    moved = _perturbed_params("kr210", 15)
    nominal = KinematicParams.from_robot(load_robot("kr210"))
    table = moved.joint_table()
    again = nominal.with_joint_table(table)
    np.testing.assert_array_equal(again.joint_table(), table)
    np.testing.assert_array_equal(again.tool_xyz_mm, nominal.tool_xyz_mm)
    np.testing.assert_array_equal(again.sign, nominal.sign)
    table[:] = 0.0
    np.testing.assert_array_equal(again.joint_table(), moved.joint_table())


def test_refuses_wrongly_shaped_inputs() -> None:
    params = KinematicParams.from_robot(load_robot("kr210"))
    with pytest.raises(ValueError, match=r"shape \(n, 6\)"):
        chain(params, np.zeros((3, 5)))
    with pytest.raises(ValueError, match="shape"):
        params.apply(np.zeros(10))
