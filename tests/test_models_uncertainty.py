"""Measurement uncertainty (seed 002, spec A.8): repeats, the c table, the nested loop, prediction std."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.estimation.uncertainty import (
    nested_correction,
    nested_factor,
    nested_identification,
    prediction_std,
    repeat_uncertainty,
    weights_from_uncertainty,
)
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, ballbar_jacobian, ballbar_lengths_mm, fit_ballbar
from comp_daemon.kinematics.poe import irb120_table1
from comp_daemon.robot.description import load_robot

MODEL = irb120_table1(load_robot("irb120")).with_tool((30.0, 20.0, 50.0))


def test_hand_worked_repeat_uncertainty() -> None:
    # deviations from the mean 100.000 mm: 0, +2, −2, +1, −1 µm → Σd² = 10 µm², u = sqrt(10/4) µm
    repeats = np.array([[100.000, 100.002, 99.998, 100.001, 99.999]])
    res = repeat_uncertainty(repeats)
    assert res.mean[0] == pytest.approx(100.0, abs=1e-12)
    assert res.u[0] == pytest.approx(np.sqrt(2.5) * 1e-3, rel=1e-9)
    assert res.b[0] == pytest.approx(1.96 * np.sqrt(2.5) * 1e-3, rel=1e-9)
    assert res.reading[0] == 99.999  # the last repeat, as in the paper
    of_mean = repeat_uncertainty(repeats, reading="mean")
    assert of_mean.u[0] == pytest.approx(np.sqrt(2.5) * 1e-3 / np.sqrt(5), rel=1e-9)
    assert of_mean.reading[0] == pytest.approx(100.0)
    with pytest.raises(ValueError, match="at least 2 repeats"):
        repeat_uncertainty(np.ones((3, 1)))


def test_weights_have_a_floor() -> None:
    w = weights_from_uncertainty(np.array([1e-3, 1e-4, 0.0]))
    np.testing.assert_allclose(w, [1e6, 4e6, 4e6])


def test_c_table() -> None:
    b = np.ones(4)
    c, flagged = nested_factor(np.array([0.2, 0.3, 0.6, 1.2]), b)
    np.testing.assert_array_equal(c, [0, 4, 2, 0])
    np.testing.assert_array_equal(flagged, [False, False, False, True])
    c_neg, _ = nested_factor(np.array([-0.3, -0.6, -0.25, -0.5]), b)
    np.testing.assert_array_equal(c_neg, [4, 2, 0, 2])


def test_correction_rules() -> None:
    a = np.array([0.2, 0.3, -0.6, 1.2])
    b = np.ones(4)
    step, _, _ = nested_correction(a, b, "step")
    np.testing.assert_allclose(step, [0.2, 0.3 - 0.25, -0.6 + 0.5, 1.2])
    divide, _, _ = nested_correction(a, b, "divide")
    np.testing.assert_allclose(divide, [0.2, 0.075, -0.3, 1.2])
    subtract, _, _ = nested_correction(a, b, "subtract")
    np.testing.assert_allclose(subtract, [0.2, 0.225, -0.3, 1.2])


def _campaign(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a_deg = rng.uniform(-35.0, 35.0, (60, 6)) + np.array([0.0, 10.0, 0.0, 0.0, 60.0, 0.0])
    truth = np.zeros(15)
    truth[[2, 3, 5, 7, 8, 9, 10, 11, 12, 13, 14]] = rng.normal(0.0, 1.0, 11) * (
        [0.3] * 3 + [0.003] * 5 + [0.5] * 3
    )
    return a_deg, truth


def test_nested_loop_ends_inside_the_quarter_band() -> None:
    a_deg, truth = _campaign(1)
    rng = np.random.default_rng(2)
    bar_true = ballbar_lengths_mm(MODEL, a_deg, truth, PAPER_PIVOT_MM)
    repeats = bar_true[:, None] + rng.normal(0.0, 0.0035, (bar_true.size, 5))
    unc = repeat_uncertainty(repeats)

    def identify(readings: np.ndarray, warm: np.ndarray | None) -> np.ndarray:
        return fit_ballbar(MODEL, a_deg, readings, PAPER_PIVOT_MM, theta0=warm).theta

    def predict(theta: np.ndarray) -> np.ndarray:
        return ballbar_lengths_mm(MODEL, a_deg, theta, PAPER_PIVOT_MM)

    res = nested_identification(identify, predict, unc.reading, unc.b)
    assert res.reason in ("converged", "unchanged")
    assert res.rounds[0].n_corrected > 0
    quiet = ~res.flagged
    assert np.all(np.abs(res.residual[quiet]) <= unc.b[quiet] / 4 + 1e-12)
    # the correction lowers the fit residual (by construction) and moves readings by less than b
    assert np.sqrt(np.mean(res.residual**2)) < res.rounds[0].h
    assert np.all(np.abs(res.readings - unc.reading) <= unc.b + 1e-12)


def test_prediction_std_matches_the_spread_of_noisy_fits() -> None:
    a_deg, truth = _campaign(3)
    a_check = _campaign(4)[0][:10]
    bar = ballbar_lengths_mm(MODEL, a_deg, truth, PAPER_PIVOT_MM)
    rng = np.random.default_rng(5)
    sigma = 0.0035
    preds, stds = [], []
    for _ in range(40):
        noisy = bar + rng.normal(0.0, sigma, bar.size)
        fit = fit_ballbar(
            MODEL,
            a_deg,
            noisy,
            PAPER_PIVOT_MM,
            weights=np.full(bar.size, 1 / sigma**2),
            weights_are_inverse_variance=True,
        )
        preds.append(ballbar_lengths_mm(MODEL, a_check, fit.theta, PAPER_PIVOT_MM))
        _, jac = ballbar_jacobian(MODEL, a_check, fit.theta, PAPER_PIVOT_MM)
        stds.append(prediction_std(jac, fit.cov))
    ratio = np.std(preds, axis=0, ddof=1) / np.mean(stds, axis=0)
    assert np.all((ratio > 0.6) & (ratio < 1.5))
