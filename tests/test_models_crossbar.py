"""Cross-bar calibration (seed 003, spec Part B): rows, rank table, recovery, weighting, step rejection."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from comp_daemon.instruments.crossbar import (
    CrossbarPlan,
    CrossbarRefusedError,
    absorb_probe,
    bar_errors_mm,
    calibrate_crossbar,
    check_plan,
    constraint_rows,
    constraint_values,
    crossbar_columns,
    crossbar_identifiability,
    plan_crossbar,
    preset_errors_b5,
    row_shortage,
    seat_probe,
)
from comp_daemon.kinematics.params import PARAM_NAMES, KinematicParams
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("mh6")
SIGN = ROBOT.sign
LIMITS = ROBOT.axis_limits_deg


def _params(tool: tuple[float, float, float] = (40.0, 0.0, 100.0)) -> KinematicParams:
    return replace(KinematicParams.from_robot(ROBOT), tool_xyz_mm=np.array(tool))


NOMINAL = absorb_probe(_params())
TRUE = NOMINAL.apply(preset_errors_b5())


def _campaign(
    params: KinematicParams, n: int, rng: np.random.Generator, sigma: float = 0.0
) -> tuple[CrossbarPlan, np.ndarray]:
    plan = plan_crossbar(2 * n, rng)
    a_deg, ok = seat_probe(params, SIGN, LIMITS, plan, noise_sigma_mm=sigma, rng=rng)
    index = np.flatnonzero(ok)[:n]
    assert index.size == n
    return plan.subset(index), a_deg[index]


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2)))


def test_probe_absorbed_into_link_six_keeps_the_tcp() -> None:
    params = _params()
    folded = absorb_probe(params)
    assert folded.a_mm[5] == pytest.approx(40.0) and folded.d_mm[5] == pytest.approx(-195.0)
    _, a_deg = _campaign(TRUE, 3, np.random.default_rng(0))
    np.testing.assert_allclose(
        constraint_values(params, a_deg, SIGN), constraint_values(folded, a_deg, SIGN), atol=1e-9
    )
    with pytest.raises(ValueError, match="tool_y"):
        absorb_probe(_params((40.0, 5.0, 100.0)))


def test_rows_match_central_differences_and_first_order_sign() -> None:
    rng = np.random.default_rng(1)
    plan, a_deg = _campaign(TRUE, 6, rng)
    x0 = NOMINAL.apply(rng.normal(0.0, 1e-3, len(PARAM_NAMES)) * (np.arange(39) < 30))
    rows, rhs = constraint_rows(x0, a_deg, SIGN, plan.bar_l_mm, weighted=False)
    cols = [PARAM_NAMES.index(n) for n in crossbar_columns(x0)]
    scale = np.abs(rows).max(axis=(0, 2))  # per constraint kind (mm/unit, mm²/unit)
    for k in cols:
        h = 1e-5 if PARAM_NAMES[k].rstrip("0123456789") in ("a", "d") else 1e-7
        e = np.zeros(len(PARAM_NAMES))
        e[k] = h
        v_plus = constraint_values(x0.apply(e), a_deg, SIGN)
        v_minus = constraint_values(x0.apply(-e), a_deg, SIGN)
        num = (v_plus - v_minus) / (2 * h)
        assert np.all(np.abs(rows[:, :, k] - num) <= 1e-6 * scale), PARAM_NAMES[k]
    # the right-hand side is the constraint's miss: L − D for distances, −e1·e2 for perpendicularity
    vals = constraint_values(x0, a_deg, SIGN)
    np.testing.assert_allclose(rhs[:, 0], plan.bar_l_mm - vals[:, 0])
    np.testing.assert_allclose(rhs[:, 2], -vals[:, 2])
    # first order: g(x0 + dx) ≈ g + row·dx (corrected sign), far from g − row·dx (printed sign)
    dx = np.zeros(len(PARAM_NAMES))
    dx[cols] = rng.normal(0.0, 1e-3, len(cols))
    g1 = constraint_values(x0.apply(dx), a_deg, SIGN)[:, 2]
    lin = rows[:, 2] @ dx
    assert np.abs(g1 - (vals[:, 2] + lin)).max() < 1e-2 * np.abs(lin).max()
    assert np.abs(g1 - (vals[:, 2] - lin)).max() > 1.5 * np.abs(lin).max()


def test_rank_table_off_and_on_axis() -> None:
    _, a_deg = _campaign(TRUE, 18, np.random.default_rng(2))
    lengths = np.full(18, 400.0)
    off = crossbar_identifiability(NOMINAL, a_deg, SIGN, lengths)
    assert len(off.candidates) == 24
    assert off.rank_svd == off.rank_qr == off.n_identifiable == 21  # the paper's count for the MH6
    assert set(off.removed_names("zero")) == {"theta1", "d1", "alpha6"}
    assert not off.removed_names("dependent")
    on = crossbar_identifiability(absorb_probe(_params((0.0, 0.0, 100.0))), a_deg, SIGN, lengths)
    assert on.rank_svd == on.n_identifiable == 18
    assert set(on.removed_names("zero")) == {"theta1", "d1", "theta6", "alpha6"}
    dependent = {r.name: r.depends_on for r in on.removed if r.reason == "dependent"}
    assert dependent == {"a5": ("theta5",), "alpha5": ("d5",)}
    product = crossbar_identifiability(_params(), a_deg, SIGN, lengths, tool=True)
    assert product.rank_svd == 21
    assert set(product.removed_names("zero")) == {"theta1", "d1"}


def test_step_bounds_by_unit() -> None:
    from comp_daemon.instruments.crossbar import _step_bounds

    bounds = _step_bounds(("theta2", "d3", "a1", "alpha1", "beta2", "tool_x"), 2.0, 0.5)
    np.testing.assert_allclose(bounds, [np.deg2rad(0.5), 2.0, 2.0, np.deg2rad(0.5), np.deg2rad(0.5), 2.0])


def test_plan_check_refuses_a_fixed_a6_and_too_few_placements() -> None:
    _, a_deg = _campaign(TRUE, 18, np.random.default_rng(3))
    check_plan(a_deg)
    fixed = a_deg.copy()
    fixed[..., 5] = 10.0
    with pytest.raises(CrossbarRefusedError, match="A6 spans"):
        check_plan(fixed)
    with pytest.raises(CrossbarRefusedError, match="unknowns need"):
        check_plan(a_deg[:13])


def test_noise_free_recovery() -> None:
    plan, a_deg = _campaign(TRUE, 18, np.random.default_rng(4))
    before = np.abs(bar_errors_mm(NOMINAL, a_deg, SIGN, plan.bar_l_mm)).max()
    fit = calibrate_crossbar(NOMINAL, a_deg, SIGN, plan.bar_l_mm)
    assert fit.iterations <= 10 and fit.reason == "step"
    kept = fit.report.identifiable_index
    assert kept.size == 21
    assert np.abs(fit.dx[kept] - preset_errors_b5()[kept]).max() < 1e-9
    assert set(fit.not_identified) == {"theta1", "d1", "alpha6"}
    assert before > 4.0
    assert np.abs(bar_errors_mm(fit.params, a_deg, SIGN, plan.bar_l_mm)).max() < 1e-6


def test_noisy_weighted_reaches_the_noise_floor() -> None:
    ratios = []
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        plan, a_deg = _campaign(TRUE, 18, rng, sigma=0.1)
        check, a_check = _campaign(TRUE, 18, rng, sigma=0.1)
        fit = calibrate_crossbar(NOMINAL, a_deg, SIGN, plan.bar_l_mm)
        floor = _rms(bar_errors_mm(TRUE, a_check, SIGN, check.bar_l_mm))
        ratios.append(_rms(bar_errors_mm(fit.params, a_check, SIGN, check.bar_l_mm)) / floor)
        assert _rms(bar_errors_mm(NOMINAL, a_check, SIGN, check.bar_l_mm)) > 5 * floor
    assert float(np.mean(ratios)) <= 1.5


def test_unweighted_gets_worse_with_more_placements() -> None:
    rng = np.random.default_rng(7)
    plan, a_deg = _campaign(TRUE, 40, rng, sigma=0.1)
    check, a_check = _campaign(TRUE, 18, rng, sigma=0.1)
    weighted = calibrate_crossbar(NOMINAL, a_deg, SIGN, plan.bar_l_mm)
    unweighted = calibrate_crossbar(NOMINAL, a_deg, SIGN, plan.bar_l_mm, weighted=False)
    err_w = _rms(bar_errors_mm(weighted.params, a_check, SIGN, check.bar_l_mm))
    err_u = _rms(bar_errors_mm(unweighted.params, a_check, SIGN, check.bar_l_mm))
    assert err_u > 3 * err_w


def test_swapped_sockets_are_rejected() -> None:
    rng = np.random.default_rng(8)
    plan, a_deg = _campaign(TRUE, 18, rng, sigma=0.1)
    check, a_check = _campaign(TRUE, 18, rng, sigma=0.1)
    clean = calibrate_crossbar(NOMINAL, a_deg, SIGN, plan.bar_l_mm)
    swapped = a_deg.copy()
    swapped[5, [0, 1]] = a_deg[5, [1, 0]]
    fit = calibrate_crossbar(NOMINAL, swapped, SIGN, plan.bar_l_mm)
    assert fit.dropped == (5,)
    err_clean = _rms(bar_errors_mm(clean.params, a_check, SIGN, check.bar_l_mm))
    err_fit = _rms(bar_errors_mm(fit.params, a_check, SIGN, check.bar_l_mm))
    assert err_fit <= 1.5 * err_clean


def test_three_rows_a_placement_and_two_rows_an_unknown() -> None:
    assert row_shortage(14, 21) is None
    assert row_shortage(13, 21) == "13 placements give 39 rows; 21 unknowns need 42"
    assert row_shortage(7, 10) is None and row_shortage(6, 10) is not None


def test_rejecting_a_placement_below_the_rows_needed_is_refused() -> None:
    plan, a_deg = _campaign(TRUE, 14, np.random.default_rng(8))
    knocked = a_deg.copy()
    knocked[5, :, 1] += 15.0  # placement 5 read with A2 15 degrees off: a step far beyond its bound
    with pytest.raises(
        CrossbarRefusedError,
        match=r"^after rejecting placements \[5\], 13 placements give 39 rows; 21 unknowns",
    ):
        calibrate_crossbar(NOMINAL, knocked, SIGN, plan.bar_l_mm)
