"""The Chebyshev error model of seed 000: forward model, Jacobian, identification, order selection."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from numpy.polynomial import chebyshev as npcheb

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import rotvec_to_matrix as rotation_from_rotvec
from comp_daemon.models.chebyshev import (
    ChebyshevModel,
    chebyshev_basis,
    chebyshev_jacobian,
    chebyshev_tcp_mm,
    coefficient_names,
    fit_chebyshev,
    n_coefficients,
    select_order,
)
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.robot.description import RobotDescription, load_robot


def _axes(robot: RobotDescription, n: int, seed: int, span: float = 0.8) -> np.ndarray:
    lim = robot.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-span, span, (n, 6)) * np.minimum(half, 120.0)


def test_basis_is_the_chebyshev_recursion() -> None:
    x = np.linspace(-1, 1, 11)
    np.testing.assert_allclose(chebyshev_basis(x, 5), npcheb.chebvander(x, 5), atol=1e-14)


def test_names_and_layout() -> None:
    names = coefficient_names(3)
    assert len(names) == n_coefficients(3) == 6 + 36 * 4
    assert names[:6] == tuple(
        f"E0.{t}.c0" for t in ("eps_x", "eps_y", "eps_z", "delta_x", "delta_y", "delta_z")
    )
    assert names[6:10] == ("E1.eps_x.c0", "E1.eps_x.c1", "E1.eps_x.c2", "E1.eps_x.c3")
    assert names[-1] == "E6.delta_z.c3"


def test_zero_coefficients_are_the_nominal_robot() -> None:
    kr = load_robot("kr210")
    params = KinematicParams.from_robot(kr)
    a = _axes(kr, 20, 0)
    p = chebyshev_tcp_mm(params, a, kr.axis_limits_deg, 3, np.zeros(n_coefficients(3)))
    np.testing.assert_allclose(p, tcp_position_mm(params, axes_deg_to_q_rad(a, kr.sign)), atol=1e-9)


def test_single_terms_act_as_differential_motions() -> None:
    """E_6's order-0 translation moves the TCP along the flange axes; E_0's along the base axes."""
    kr = load_robot("kr210")
    params = KinematicParams.from_robot(kr)
    a = _axes(kr, 5, 1)
    names = coefficient_names(1)
    coef = np.zeros(len(names))
    coef[names.index("E0.delta_y.c0")] = 0.3
    coef[names.index("E6.delta_z.c0")] = 0.2
    p = chebyshev_tcp_mm(params, a, kr.axis_limits_deg, 1, coef)
    flange_z = np.array([0.0, 0.0, 0.2])
    moved = replace(params, tool_xyz_mm=params.tool_xyz_mm + flange_z)
    expected = tcp_position_mm(moved, axes_deg_to_q_rad(a, kr.sign)) + np.array([0.0, 0.3, 0.0])
    np.testing.assert_allclose(p, expected, atol=1e-9)


@pytest.mark.parametrize("order", [0, 2])
def test_jacobian_matches_central_differences(order: int) -> None:
    kr = load_robot("kr210")
    params = KinematicParams.from_robot(kr).with_base(np.eye(4))
    a = _axes(kr, 8, 2)
    rng_deg = kr.axis_limits_deg
    coef = np.random.default_rng(3).normal(size=n_coefficients(order)) * 1e-3
    jac = chebyshev_jacobian(params, a, rng_deg, order, coef)
    num = np.empty_like(jac)
    for k in range(coef.size):
        e = np.zeros_like(coef)
        e[k] = 1e-5
        num[:, :, k] = (
            chebyshev_tcp_mm(params, a, rng_deg, order, coef + e)
            - chebyshev_tcp_mm(params, a, rng_deg, order, coef - e)
        ) / 2e-5
    scale = np.abs(jac).max(axis=(0, 1))
    assert np.all(np.abs(jac - num) <= 1e-7 * scale[None, None, :] + 1e-7)


def test_order_zero_matches_the_kinematic_calibration() -> None:
    """Order 0 is the geometric error model: the fit and predictions of the MDH calibration.

    Equal to first order in the errors: E_i = I + Δ is the differential (linear) transformation,
    so with 1 mrad errors on a 2 m arm the two differ by about (1e-3)²·2000 mm = 2 µm.
    """
    kr = load_robot("kr210")
    rng = np.random.default_rng(4)
    dx = rng.normal(size=N_PARAMS) * 1e-3
    truth = KinematicParams.from_robot(kr).apply(dx)
    a = _axes(kr, 150, 5)
    p = tcp_position_mm(truth, axes_deg_to_q_rad(a, kr.sign)) + rng.normal(size=(150, 3)) * 0.01
    cheb = fit_chebyshev(kr, a[:100], p[:100], 0)
    kin = calibrate_kinematic(kr, a[:100], p[:100])
    assert cheb.report.n_identifiable == kin.report.n_identifiable == 27
    assert cheb.rms_mm == pytest.approx(kin.rms_mm, rel=5e-3)
    diff = cheb.model.predict_tcp_mm(a[100:]) - kin.model.predict_tcp_mm(a[100:])
    assert np.abs(diff).max() < 1e-2


def test_noise_free_chebyshev_errors_are_recovered() -> None:
    """Data made by the model itself, on coefficients the data identify, are fitted exactly."""
    kr = load_robot("kr210")
    a = _axes(kr, 400, 6)
    rng_deg = np.array([a.min(axis=0), a.max(axis=0)]).T
    order = 2
    probe = fit_chebyshev(
        kr, a, tcp_position_mm(KinematicParams.from_robot(kr), axes_deg_to_q_rad(a, kr.sign)), order
    )
    idx = probe.report.identifiable_index
    coef = np.zeros(n_coefficients(order))
    rng = np.random.default_rng(7)
    names = np.array(coefficient_names(order))
    is_rot = np.array([".eps_" in n for n in names])
    coef[idx] = rng.normal(size=idx.size) * np.where(is_rot[idx], 2e-4, 0.1)
    p = chebyshev_tcp_mm(KinematicParams.from_robot(kr), a, rng_deg, order, coef)
    fit = fit_chebyshev(kr, a, p, order, frame="base")
    assert fit.lm.converged
    assert fit.rms_mm < 1e-8
    np.testing.assert_allclose(fit.model.coefficients[idx], coef[idx], rtol=1e-6, atol=1e-10)
    assert np.all(fit.model.coefficients[~fit.model.active] == 0.0)


def _cyclic_robot(kr: RobotDescription) -> tuple[EffectParams, np.ndarray]:
    rng = np.random.default_rng(8)
    truth = KinematicParams.from_robot(kr).apply(rng.normal(size=N_PARAMS) * 5e-4)
    eff = EffectParams.zeros(2).with_values(["c2_1", "s3_2", "eps2"], [0.01, 0.008, 3e-4])
    return eff, truth


def test_cross_validation_prefers_higher_orders_for_angle_dependent_errors() -> None:
    kr = load_robot("kr210")
    eff, truth = _cyclic_robot(kr)
    a = _axes(kr, 240, 9, span=0.5)
    p = twin_tcp_mm(kr, truth, eff, a) + np.random.default_rng(10).normal(size=(240, 3)) * 0.005
    sel = select_order(kr, a[:160], p[:160], orders=(0, 2), rtols=(0.2,), folds=3)
    assert sel.order == 2
    assert sel.cv_rms_mm[1][0] < 0.7 * sel.cv_rms_mm[0][0]
    fit = fit_chebyshev(kr, a[:160], p[:160], sel.order, rtol=sel.rtol)
    kin = calibrate_kinematic(kr, a[:160], p[:160])
    err_cheb = np.linalg.norm(fit.model.predict_tcp_mm(a[160:]) - p[160:], axis=1)
    err_kin = np.linalg.norm(kin.model.predict_tcp_mm(a[160:]) - p[160:], axis=1)
    assert np.sqrt(np.mean(err_cheb**2)) < 0.7 * np.sqrt(np.mean(err_kin**2))


def test_weak_coefficients_are_removed_not_left_to_explode() -> None:
    """A high order on few noisy rows: removed by name, the rest stay physically small."""
    kr = load_robot("kr210")
    eff, truth = _cyclic_robot(kr)
    a = _axes(kr, 140, 11, span=0.3)
    p = twin_tcp_mm(kr, truth, eff, a) + np.random.default_rng(12).normal(size=(140, 3)) * 0.03
    fit = fit_chebyshev(kr, a[:70], p[:70], 4)
    names = np.array(fit.model.names)
    assert fit.report.n_identifiable < len(names)
    assert set(fit.report.removed_names()) == set(names[~fit.model.active])
    assert np.all(fit.model.coefficients[~fit.model.active] == 0.0)
    eps = np.array([".eps_" in n for n in names])
    assert np.abs(fit.model.coefficients[eps]).max() < 0.05  # rad
    assert np.abs(fit.model.coefficients[~eps]).max() < 20.0  # mm
    kin = calibrate_kinematic(kr, a[:70], p[:70])
    err = np.linalg.norm(fit.model.predict_tcp_mm(a[70:]) - p[70:], axis=1)
    err_kin = np.linalg.norm(kin.model.predict_tcp_mm(a[70:]) - p[70:], axis=1)
    assert np.sqrt(np.mean(err**2)) < 1.2 * np.sqrt(np.mean(err_kin**2))
    assert err.max() < 1.5 * err_kin.max()


def test_tracker_frame_is_registered_first() -> None:
    """The same robot measured in a tracker frame fits as well as in its base frame."""
    kr = load_robot("kr210")
    eff, truth = _cyclic_robot(kr)
    world = np.eye(4)
    world[:3, :3] = rotation_from_rotvec(np.array([0.0, 0.1, 2.0]))
    world[:3, 3] = [4000.0, -2500.0, 300.0]
    a = _axes(kr, 150, 13)
    p_base = twin_tcp_mm(kr, truth, eff, a)
    p_world = p_base @ world[:3, :3].T + world[:3, 3]
    in_base = fit_chebyshev(kr, a, p_base, 2)
    in_world = fit_chebyshev(kr, a, p_world, 2)
    assert (in_base.frame, in_world.frame) == ("base", "tracker")
    assert in_world.rms_mm == pytest.approx(in_base.rms_mm, rel=1e-2)
    a_new = _axes(kr, 20, 15)
    pred_world = in_world.model.predict_tcp_mm(a_new)
    pred_base = in_base.model.predict_tcp_mm(a_new) @ world[:3, :3].T + world[:3, 3]
    assert np.abs(pred_world - pred_base).max() < 0.01


def test_outside_the_range_the_error_is_held_at_the_edge() -> None:
    kr = load_robot("kr210")
    names = coefficient_names(2)
    coef = np.zeros(len(names))
    coef[names.index("E1.delta_x.c2")] = 0.5
    rng = np.array([[-50.0, 50.0], *kr.axis_limits_deg[1:]])
    model = ChebyshevModel(kr, np.eye(4), 2, rng, coef)
    a = _axes(kr, 1, 14)
    inside, edge, beyond = a.copy(), a.copy(), a.copy()
    inside[0, 0], edge[0, 0], beyond[0, 0] = 10.0, 50.0, 80.0
    assert not model.outside_range(edge)[0] and model.outside_range(beyond)[0]
    err_edge = model.predict_tcp_mm(edge) - _nominal_tcp(kr, edge)
    err_beyond = model.predict_tcp_mm(beyond) - _nominal_tcp(kr, beyond)
    assert np.linalg.norm(err_edge) == pytest.approx(0.5, rel=1e-6)
    assert np.linalg.norm(err_beyond) == pytest.approx(0.5, rel=1e-6)


def _nominal_tcp(robot: RobotDescription, a: np.ndarray) -> np.ndarray:
    return tcp_position_mm(KinematicParams.from_robot(robot), axes_deg_to_q_rad(a, robot.sign))


def test_bad_model_content_is_refused() -> None:
    kr = load_robot("kr210")
    with pytest.raises(ValueError, match="order 1 needs 78 coefficients"):
        ChebyshevModel(kr, np.eye(4), 1, kr.axis_limits_deg, np.zeros(5))
    with pytest.raises(ValueError, match="low < high"):
        ChebyshevModel(kr, np.eye(4), 0, np.zeros((6, 2)), np.zeros(42))


def test_measured_positions_not_finite_or_of_another_shape_are_refused_by_name() -> None:
    kr = load_robot("kr210")
    a = _axes(kr, 40, seed=9)
    params = KinematicParams.from_robot(kr)
    p = tcp_position_mm(params, axes_deg_to_q_rad(a, params.sign))
    p[3, 1] = np.nan
    with pytest.raises(ValueError, match="measured positions must be finite"):
        calibrate_kinematic(kr, a, p)
    with pytest.raises(ValueError, match="measured positions must be finite"):
        fit_chebyshev(kr, a, p, 1)
    with pytest.raises(ValueError, match=r"measured positions must have shape \(40, 3\), got \(39, 3\)"):
        fit_chebyshev(kr, a, p[:39], 1)
