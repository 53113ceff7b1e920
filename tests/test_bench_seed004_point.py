"""Seed 004's point-constraint zero-offset calibration with joint compliance (laser lines through a PSD),
the benchmark that reproduces the paper's experiment (``benchmarks/seed004_*.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.seed004_compliance import (
    SEED004_COMPLIANCE_RAD_PER_NM,
    SEED004_ZERO_OFFSETS_DEG,
    PsdPoses,
    PsdSetup,
    _link5_shift,
    average_models,
    reproduce_seed004,
    simulate_psd_poses,
)
from benchmarks.seed004_point import (
    calibrate_point_constraint,
    laser_lines,
    line_distance_errors_mm,
    point_constraint_jacobian,
    psd_distance_errors_mm,
)
from benchmarks.seed004_variations import VARIATIONS, Variation, run_variation
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.compliance import ComplianceModel
from comp_daemon.models.effects import EffectParams, MassModel, twin_state
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")
SETUP = PsdSetup()


def _true_params() -> KinematicParams:
    dx = np.zeros(N_PARAMS)
    dx[0:30:5] = np.deg2rad(SEED004_ZERO_OFFSETS_DEG)
    return KinematicParams.from_robot(ROBOT).apply(dx)


@pytest.fixture(scope="module")
def poses() -> PsdPoses:
    return simulate_psd_poses(
        ROBOT,
        _true_params(),
        SEED004_COMPLIANCE_RAD_PER_NM,
        SETUP,
        28,
        np.random.default_rng(1),
        link5_noise_mm=0.0,
    )


def test_simulated_poses_put_the_true_beam_through_the_psd_centre() -> None:
    true = _true_params()
    comp = np.array(SEED004_COMPLIANCE_RAD_PER_NM)
    sim = simulate_psd_poses(ROBOT, true, comp, SETUP, 12, np.random.default_rng(2), link5_noise_mm=1.0)
    assert np.all((sim.link5_delta_mm >= 0.0) & (sim.link5_delta_mm <= 1.0))
    o, u = laser_lines(ROBOT, true, comp, sim.a_deg, SETUP.mount)
    # the link-5 error of each pose moves the beam origin without turning the beam
    st = twin_state(MassModel.from_robot(ROBOT), true, EffectParams(compliance_rad_per_nm=comp), sim.a_deg)
    o = o + _link5_shift(true, st.q_rad, sim.link5_delta_mm)
    w = SETUP.center_mm - o
    miss = np.linalg.norm(w - u * np.einsum("ni,ni->n", u, w)[:, None], axis=1)
    assert miss.max() < 1e-6
    lim = ROBOT.axis_limits_deg
    assert np.all((sim.a_deg >= lim[:, 0]) & (sim.a_deg <= lim[:, 1]))


def test_link5_shift_equals_forward_kinematics_with_changed_a5_d5() -> None:
    from dataclasses import replace

    from comp_daemon.kinematics.forward import tcp_position_mm

    p = replace(KinematicParams.from_robot(ROBOT), tool_xyz_mm=np.array([10.0, 20.0, 30.0]))
    q = np.deg2rad([[10.0, 20.0, -15.0, 30.0, 50.0, 70.0]])
    delta = np.array([[0.7, -0.4]])
    moved = replace(
        p, a_mm=p.a_mm + np.array([0, 0, 0, 0, 0.7, 0]), d_mm=p.d_mm + np.array([0, 0, 0, 0, -0.4, 0])
    )
    np.testing.assert_allclose(
        tcp_position_mm(moved, q) - tcp_position_mm(p, q), _link5_shift(p, q, delta), atol=1e-10
    )


def test_point_constraint_jacobian_matches_central_differences(poses: PsdPoses) -> None:
    rng = np.random.default_rng(3)
    dx0 = np.zeros(N_PARAMS)
    dx0[0:30:5] = rng.normal(0.0, 0.01, 6)
    params = _true_params().apply(dx0)
    comp = np.array([0.0, 4e-5, 2e-5, 0.0, 0.0, 0.0])
    point = SETUP.center_mm + np.array([1.0, -2.0, 0.5])  # not on the lines: the general case
    a = poses.a_deg[:5]
    _, jac = point_constraint_jacobian(ROBOT, params, comp, a, SETUP.mount, point)
    h_theta, h_c, h_p = 1e-7, 1e-9, 1e-4
    # zero-offset columns: exact without compliance; with it, exact up to C·dτ/dθ (the torque's own
    # dependence on the offsets, left out as in comp_daemon.models.effects), below 1e-2 here
    _, jac0 = point_constraint_jacobian(ROBOT, params, np.zeros(6), a, SETUP.mount, point)
    for c, jj, rtol in ((np.zeros(6), jac0, 1e-6), (comp, jac, 1e-2)):
        for k in range(6):
            dx = np.zeros(N_PARAMS)
            dx[5 * k] = h_theta
            rp, _ = point_constraint_jacobian(ROBOT, params.apply(dx), c, a, SETUP.mount, point)
            rm, _ = point_constraint_jacobian(ROBOT, params.apply(-dx), c, a, SETUP.mount, point)
            num = (rp - rm) / (2 * h_theta)
            assert np.abs(jj[:, :, k] - num).max() <= rtol * np.abs(num).max() + 1e-6
    for k, j in enumerate((2, 3)):
        dc = np.zeros(6)
        dc[j - 1] = h_c
        rp, _ = point_constraint_jacobian(ROBOT, params, comp + dc, a, SETUP.mount, point)
        rm, _ = point_constraint_jacobian(ROBOT, params, comp - dc, a, SETUP.mount, point)
        np.testing.assert_allclose(jac[:, :, 6 + k], (rp - rm) / (2 * h_c), rtol=1e-5, atol=1e-3)
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h_p
        rp, _ = point_constraint_jacobian(ROBOT, params, comp, a, SETUP.mount, point + dp)
        rm, _ = point_constraint_jacobian(ROBOT, params, comp, a, SETUP.mount, point - dp)
        np.testing.assert_allclose(jac[:, :, 8 + k], (rp - rm) / (2 * h_p), rtol=1e-7, atol=1e-9)


def test_seven_noise_free_poses_recover_offsets_and_compliance_and_theta1_is_unidentifiable(
    poses: PsdPoses,
) -> None:
    fit = calibrate_point_constraint(ROBOT, poses.a_deg[:7], SETUP.mount)
    report = fit.fit.report
    assert report.removed_names() == ("theta1",)
    removed = report.removed[0]
    assert removed.reason == "dependent" and set(removed.depends_on) <= {"P_x", "P_y", "P_z"}
    model = fit.model
    np.testing.assert_allclose(
        np.rad2deg(model.zero_offset_rad[1:]), np.array(SEED004_ZERO_OFFSETS_DEG[1:]), atol=1e-8
    )
    np.testing.assert_allclose(
        model.compliance_rad_per_nm, SEED004_COMPLIANCE_RAD_PER_NM, rtol=1e-6, atol=1e-12
    )
    np.testing.assert_allclose(fit.point_mm, SETUP.center_mm, atol=1e-6)
    assert fit.fit.rms_mm < 1e-9


def test_without_compliance_the_original_model_leaves_an_error_the_improved_one_removes(
    poses: PsdPoses,
) -> None:
    a_fit, a_chk = poses.a_deg[:14], poses.a_deg[14:]
    zero = calibrate_point_constraint(ROBOT, a_fit, SETUP.mount, compliance_joints=()).model
    comp = calibrate_point_constraint(ROBOT, a_fit, SETUP.mount).model
    assert np.all(zero.compliance_rad_per_nm == 0.0)
    nominal = ComplianceModel(ROBOT, np.zeros(6), np.zeros(6))
    err = {
        name: psd_distance_errors_mm(m, a_chk, SETUP.mount, SETUP.center_mm, SETUP.normal).mean()
        for name, m in (("nominal", nominal), ("zero", zero), ("comp", comp))
    }
    assert err["nominal"] > 5.0  # degrees of zero offset
    assert 0.05 < err["zero"] < 1.0  # the unmodelled deflection of joints 2 and 3
    assert err["comp"] < 1e-6


def test_reproduction_of_the_papers_simulation_orders_the_models_like_the_paper() -> None:
    """420 poses, 210 calibrate (30 × 7, averaged) and 210 validate, small link-5 noise."""
    result = reproduce_seed004(seed=0, link5_noise_mm=0.1)
    assert result.compliance_mm < 0.5 * result.zero_offset_mm < result.uncompensated_mm
    assert result.compliance_joint_mm < 0.5 * result.zero_offset_joint_mm
    table = result.table()
    assert table["paper_mm"] == {"zero_offset": 0.9692, "compliance": 0.5772}
    assert table["rows"] == {"fit": 210, "check": 210}
    # the spread of the 30 seven-pose calibrations, and the true model's floor: the noise alone
    assert set(result.calibration_sd) == {"C2_rad_per_nm", "C3_rad_per_nm", "theta2_deg", "theta3_deg"}
    assert 0.0 < result.calibration_sd["C2_rad_per_nm"] < 1e-3
    assert 0.0 < result.true_model_mm < result.zero_offset_mm
    lo, hi = result.torque_range_nm["tau2"]
    assert lo < hi and table["torque_range_nm"]["tau2"] == [round(lo, 2), round(hi, 2)]


def test_a_known_point_makes_theta1_identifiable() -> None:
    offsets = np.array([0.5, *SEED004_ZERO_OFFSETS_DEG[1:]])
    dx = np.zeros(N_PARAMS)
    dx[0:30:5] = np.deg2rad(offsets)
    true = KinematicParams.from_robot(ROBOT).apply(dx)
    comp = np.array(SEED004_COMPLIANCE_RAD_PER_NM)
    sim = simulate_psd_poses(ROBOT, true, comp, SETUP, 7, np.random.default_rng(4), link5_noise_mm=0.0)
    known = calibrate_point_constraint(ROBOT, sim.a_deg, SETUP.mount, point_mm=SETUP.center_mm)
    assert known.fit.report.removed_names() == ()
    assert "P_x" not in known.fit.identified
    np.testing.assert_allclose(np.rad2deg(known.model.zero_offset_rad), offsets, atol=1e-8)
    np.testing.assert_allclose(known.model.compliance_rad_per_nm, comp, rtol=1e-6, atol=1e-12)
    np.testing.assert_array_equal(known.point_mm, SETUP.center_mm)
    unknown = calibrate_point_constraint(ROBOT, sim.a_deg, SETUP.mount)
    assert unknown.fit.report.removed_names() == ("theta1",)


def test_noise_kinds_and_blocks() -> None:
    true = _true_params()
    comp = np.array(SEED004_COMPLIANCE_RAD_PER_NM)
    centred = simulate_psd_poses(
        ROBOT, true, comp, SETUP, 40, np.random.default_rng(5), link5_noise_mm=2.0, noise="centred"
    )
    assert np.all(np.abs(centred.link5_delta_mm) <= 1.0)
    assert np.any(centred.link5_delta_mm < 0.0)
    blocks = simulate_psd_poses(ROBOT, true, comp, SETUP, 17, np.random.default_rng(6), noise_block=7)
    d = blocks.link5_delta_mm
    assert d.shape == (17, 2)
    for start in (0, 7, 14):
        np.testing.assert_array_equal(
            d[start : start + 7], np.repeat(d[start : start + 1], len(d[start : start + 7]), 0)
        )
    assert not np.array_equal(d[0], d[7])
    # every pose still puts its (noisy) true beam through the PSD centre
    o, u = laser_lines(ROBOT, true, comp, blocks.a_deg, SETUP.mount)
    st = twin_state(MassModel.from_robot(ROBOT), true, EffectParams(compliance_rad_per_nm=comp), blocks.a_deg)
    o = o + _link5_shift(true, st.q_rad, d)
    w = SETUP.center_mm - o
    assert np.linalg.norm(w - u * np.einsum("ni,ni->n", u, w)[:, None], axis=1).max() < 1e-6


def test_median_averaging_and_the_line_distance(poses: PsdPoses) -> None:
    models = [ComplianceModel(ROBOT, np.full(6, x), np.full(6, 10.0 * x)) for x in (0.0, 1e-3, 5e-3)]
    np.testing.assert_allclose(average_models(models, "median").zero_offset_rad, 1e-3)
    np.testing.assert_allclose(average_models(models).zero_offset_rad, 2e-3)
    np.testing.assert_allclose(average_models(models, "median").compliance_rad_per_nm, 1e-2)
    true = ComplianceModel(ROBOT, np.deg2rad(SEED004_ZERO_OFFSETS_DEG), SEED004_COMPLIANCE_RAD_PER_NM)
    assert line_distance_errors_mm(true, poses.a_deg, SETUP.mount, SETUP.center_mm).max() < 1e-6
    nominal = ComplianceModel(ROBOT, np.zeros(6), np.zeros(6))
    line = line_distance_errors_mm(nominal, poses.a_deg, SETUP.mount, SETUP.center_mm)
    plane = psd_distance_errors_mm(nominal, poses.a_deg, SETUP.mount, SETUP.center_mm, SETUP.normal)
    # the perpendicular distance is the shortest from the centre to the beam
    assert np.all(line <= plane + 1e-9) and line.min() > 1.0


def test_variation_table_runs_each_assumption_over_seeds() -> None:
    names = [v.name for v in VARIATIONS]
    assert names[0] == "paper" and VARIATIONS[0].kwargs == {} and len(set(names)) == len(names)
    quiet = Variation("quiet", "no noise", {"n_poses": 56, "n_fit": 28, "link5_noise_mm": 0.0})
    row = run_variation(quiet, [0, 1])
    assert row.values_mm.shape == (2, 6) and row.c2.shape == (2, 2)
    np.testing.assert_allclose(row.c2, 5.921122, rtol=1e-5)  # noise-free: C2 recovered
    assert np.all(row.values_mm[:, 1] < 1e-6)  # the true model
    assert np.all(row.values_mm[:, 3] < 1e-6) and np.all(row.values_mm[:, 2] > 0.05)
    assert row.improved_wins() == 2
    assert row.markdown().startswith("| quiet | no noise | ") and row.markdown().endswith("| 2/2 |")


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match=r"compliance_joints: joints are numbered 1\.\.6"):
        calibrate_point_constraint(ROBOT, np.zeros((7, 6)), SETUP.mount, compliance_joints=(7,))
    with pytest.raises(ValueError, match="multiple of poses_per_calibration"):
        reproduce_seed004(n_poses=40, n_fit=20, poses_per_calibration=7)
    with pytest.raises(ValueError, match="error must be"):
        reproduce_seed004(error="pixels")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="noise must be"):
        simulate_psd_poses(
            ROBOT,
            _true_params(),
            np.zeros(6),
            SETUP,
            3,
            np.random.default_rng(0),
            noise="normal",  # type: ignore[arg-type]
        )
    with pytest.raises(ValueError, match="noise_block must be"):
        simulate_psd_poses(
            ROBOT, _true_params(), np.zeros(6), SETUP, 3, np.random.default_rng(0), noise_block=0
        )
    with pytest.raises(ValueError, match="averaging must be"):
        average_models([ComplianceModel(ROBOT, np.zeros(6), np.zeros(6))], "mode")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"LaserMount\.direction must not be zero"):
        from benchmarks.seed004_point import LaserMount

        LaserMount(direction=np.zeros(3))
