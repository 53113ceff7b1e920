"""POE identification from positions (seed 002, spec A.2–A.3): ranks, named dependencies, recovery."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.kinematics.poe import POE_PARAM_NAMES, irb120_table1
from comp_daemon.kinematics.so3 import rotvec_to_matrix
from comp_daemon.models.poe.calibration import (
    BASE_NAMES,
    fit_poe_positions,
    null_directions,
    poe_identifiability,
    poe_world_jacobian,
    poe_world_position_mm,
    rms_distance_mm,
)
from comp_daemon.models.poe.twist import fit_poe_twists
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")


def _poses(n: int, seed: int) -> np.ndarray:
    lim = ROBOT.axis_limits_deg
    return np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], (n, 6))


@pytest.mark.parametrize(
    ("tool", "fit_base", "rank_of_12", "removed"),
    [
        ((0.0, 0.0, 0.0), False, 9, {"dl1", "dl5", "dtheta6"}),
        ((30.0, 20.0, 50.0), False, 10, {"dl1", "dl5"}),
        ((0.0, 0.0, 0.0), True, 7, {"dl1", "dl2", "dl5", "dtheta1", "dtheta6"}),
        ((30.0, 20.0, 50.0), True, 8, {"dl1", "dl2", "dl5", "dtheta1"}),
    ],
)
def test_ranks_and_removed_names(
    tool: tuple[float, float, float], fit_base: bool, rank_of_12: int, removed: set[str]
) -> None:
    model = irb120_table1(ROBOT).with_tool(tool)
    names = POE_PARAM_NAMES + (BASE_NAMES if fit_base else ())
    _, jac = poe_world_jacobian(model, _poses(60, 0), np.zeros(len(names)), np.eye(4) if fit_base else None)
    report = poe_identifiability(jac.reshape(-1, len(names)), names, BASE_NAMES if fit_base else ())
    extra = 6 if fit_base else 0
    assert report.rank_svd == report.rank_qr == rank_of_12 + extra
    assert set(report.removed_names()) == removed
    by_name = {r.name: r for r in report.removed}
    assert by_name["dl5"].depends_on == ("dl6",)
    assert by_name["dl5"].coefficients[0] == pytest.approx(1.0, abs=1e-9)
    if not fit_base:
        assert by_name["dl1"].depends_on == ("dl2",)
    null = null_directions(report, jac)
    assert len(null) == len(removed)
    assert all(d.singular_value < 1e-9 for d in null)


def _truth(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, [0.3] * 6 + [0.002] * 6)


def test_recovery_in_base_frame_to_noise_level() -> None:
    model = irb120_table1(ROBOT).with_tool((30.0, 20.0, 50.0))
    a_deg = _poses(80, 1)
    x_true = _truth(2)
    sigma = 0.005
    rng = np.random.default_rng(3)
    p_meas = poe_world_position_mm(model, a_deg, x_true) + rng.normal(0.0, sigma, (80, 3))
    fit = fit_poe_positions(model, a_deg, p_meas)
    assert set(fit.report.removed_names()) == {"dl1", "dl5"}
    assert fit.value("dl1") == 0.0 and fit.value("dl5") == 0.0
    expected = x_true.copy()
    expected[1] += x_true[0]  # dl2 carries dl1 + dl2
    expected[5] += x_true[4]  # dl6 carries dl5 + dl6
    kept = fit.report.identifiable_index
    err = np.abs(fit.theta[kept] - expected[kept])
    assert np.all(err < 4.0 * fit.std[kept])
    assert fit.rms_before_mm > 0.2
    assert fit.rms_after_mm < 1.3 * sigma * np.sqrt(3.0)
    # fresh poses: predicted to well below the noise
    a_check = _poses(40, 4)
    diff = poe_world_position_mm(model, a_check, fit.x) - poe_world_position_mm(model, a_check, x_true)
    assert np.sqrt(np.mean(np.sum(diff**2, axis=1))) < sigma


def test_recovery_in_tracker_frame_noise_free() -> None:
    model = irb120_table1(ROBOT)
    a_deg = _poses(60, 5)
    x_true = _truth(6)
    world_T_base = np.eye(4)
    world_T_base[:3, :3] = rotvec_to_matrix(np.array([0.1, -0.2, 0.5]))
    world_T_base[:3, 3] = [1500.0, -400.0, 250.0]
    p_meas = poe_world_position_mm(model, a_deg, x_true, world_T_base)
    fit = fit_poe_positions(model, a_deg, p_meas, fit_base=True)
    assert fit.rms_after_mm < 1e-8
    assert set(fit.report.removed_names()) == {"dl1", "dl2", "dl5", "dtheta1", "dtheta6"}
    for name in ("dl3", "dl4", "dtheta2", "dtheta3", "dtheta4", "dtheta5"):
        assert fit.value(name) == pytest.approx(x_true[POE_PARAM_NAMES.index(name)], abs=1e-8)
    assert fit.value("dl6") == pytest.approx(x_true[4] + x_true[5], abs=1e-8)
    assert fit.world_T_base is not None
    a_check = _poses(30, 7)
    diff = poe_world_position_mm(model, a_check, fit.x, fit.world_T_base) - poe_world_position_mm(
        model, a_check, x_true, world_T_base
    )
    assert np.abs(diff).max() < 1e-7


def test_world_jacobian_matches_central_differences() -> None:
    model = irb120_table1(ROBOT).with_tool((30.0, 20.0, 50.0))
    a_deg = _poses(10, 8)
    start = np.eye(4)
    start[:3, :3] = rotvec_to_matrix(np.array([0.3, 0.1, -0.4]))
    start[:3, 3] = [100.0, 20.0, -30.0]
    theta = np.concatenate([_truth(9), [0.5, -0.2, 0.1, 0.02, -0.03, 0.05]])
    _, jac = poe_world_jacobian(model, a_deg, theta, start)
    for k in range(18):
        h = 1e-4 if k < 6 or 12 <= k < 15 else 1e-6
        e = np.zeros(18)
        e[k] = h
        num = (
            poe_world_jacobian(model, a_deg, theta + e, start)[0]
            - poe_world_jacobian(model, a_deg, theta - e, start)[0]
        ) / (2 * h)
        assert np.abs(jac[:, :, k] - num).max() <= 1e-6 * max(np.abs(num).max(), 1.0)


def test_weights_downweight_a_bad_point() -> None:
    model = irb120_table1(ROBOT).with_tool((30.0, 20.0, 50.0))
    a_deg = _poses(40, 10)
    x_true = _truth(11)
    p_meas = poe_world_position_mm(model, a_deg, x_true)
    p_meas[0] += 2.0  # one gross reading
    weights = np.ones(40)
    unweighted = fit_poe_positions(model, a_deg, p_meas)
    weights[0] = 1e-8
    weighted = fit_poe_positions(model, a_deg, p_meas, weights=weights)
    kept = weighted.report.identifiable_index
    expected = x_true.copy()
    expected[1] += x_true[0]
    expected[5] += x_true[4]
    err_w = np.abs(weighted.theta[kept] - expected[kept]).max()
    err_u = np.abs(unweighted.theta[kept] - expected[kept]).max()
    assert err_w < 1e-3 < err_u


def test_both_position_fits_refuse_positions_that_do_not_match_the_axis_values() -> None:
    model = irb120_table1(ROBOT)
    a = _poses(5, 0)
    for fit in (fit_poe_positions, fit_poe_twists):
        with pytest.raises(ValueError, match=r"positions must be \(n, 3\) with n = 5, got \(4, 3\)"):
            fit(model, a, np.zeros((4, 3)))


def test_rms_distance_is_over_points_not_coordinates() -> None:
    # two points, 5 mm and 0 mm off: RMS distance sqrt(25 / 2), not the RMS of the six coordinates
    residual = np.array([3.0, 4.0, 0.0, 0.0, 0.0, 0.0])
    assert rms_distance_mm(residual) == pytest.approx(np.sqrt(12.5))
    model = irb120_table1(ROBOT)
    a = _poses(12, 1)
    shifted = poe_world_position_mm(model, a, np.zeros(12)) + np.array([3.0, 4.0, 0.0])
    for fit in (fit_poe_positions(model, a, shifted), fit_poe_twists(model, a, shifted, np.eye(4))):
        assert fit.rms_before_mm == pytest.approx(5.0)
