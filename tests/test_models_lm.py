"""The improved Levenberg–Marquardt method of seed 000 on standard least-squares problems."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.optimize import least_squares

from comp_daemon.estimation import lm
from comp_daemon.estimation.lm import improved_lm

Vec = NDArray[np.float64]


def rosenbrock(x: Vec) -> Vec:
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def rosenbrock_jac(x: Vec) -> Vec:
    return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])


def powell_singular(x: Vec) -> Vec:
    return np.array(
        [
            x[0] + 10 * x[1],
            np.sqrt(5) * (x[2] - x[3]),
            (x[1] - 2 * x[2]) ** 2,
            np.sqrt(10) * (x[0] - x[3]) ** 2,
        ]
    )


def powell_singular_jac(x: Vec) -> Vec:
    u, v = x[1] - 2 * x[2], x[0] - x[3]
    s5, s10 = np.sqrt(5), np.sqrt(10)
    return np.array(
        [[1, 10, 0, 0], [0, 0, s5, -s5], [0, 2 * u, -4 * u, 0], [2 * s10 * v, 0, 0, -2 * s10 * v]],
        dtype=float,
    )


# Osborne's exponential fit (MGH problem 19 is the large one; this is Osborne 1, a non-zero residual)
OSBORNE_Y = np.array(
    [0.844, 0.908, 0.932, 0.936, 0.925, 0.908, 0.881, 0.850, 0.818, 0.784, 0.751, 0.718, 0.685, 0.658,
     0.628, 0.603, 0.580, 0.558, 0.538, 0.522, 0.506, 0.490, 0.478, 0.467, 0.457, 0.448, 0.438, 0.431,
     0.424, 0.420, 0.414, 0.411, 0.406]
)  # fmt: skip
OSBORNE_T = 10.0 * np.arange(33)


def osborne1(x: Vec) -> Vec:
    return x[0] + x[1] * np.exp(-x[3] * OSBORNE_T) + x[2] * np.exp(-x[4] * OSBORNE_T) - OSBORNE_Y


def osborne1_jac(x: Vec) -> Vec:
    e3, e4 = np.exp(-x[3] * OSBORNE_T), np.exp(-x[4] * OSBORNE_T)
    return np.stack([np.ones_like(OSBORNE_T), e3, e4, -x[1] * OSBORNE_T * e3, -x[2] * OSBORNE_T * e4], axis=1)


def test_rosenbrock_as_least_squares_reaches_the_minimum() -> None:
    res = improved_lm(rosenbrock, rosenbrock_jac, np.array([-1.2, 1.0]))
    assert res.converged
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-10)
    assert res.cost < 1e-20
    assert res.iterations < 100


def test_each_iteration_takes_one_jacobian_and_three_extra_residuals() -> None:
    res = improved_lm(rosenbrock, rosenbrock_jac, np.array([-1.2, 1.0]))
    # F(x0) once, then F(y_k), F(z_k), F(x_k + s_k) per iteration; J at x0 and after each accepted step
    assert res.n_residual_evals == 1 + 3 * res.iterations
    accepted = sum(h.accepted for h in res.history)
    assert res.n_jacobian_evals <= 1 + accepted


def test_damping_adapts_to_the_ratio() -> None:
    res = improved_lm(rosenbrock, rosenbrock_jac, np.array([-1.2, 1.0]), upsilon1=1e-2)
    hist = res.history
    for before, after in itertools.pairwise(hist):
        if before.ratio < 0.25:
            assert after.upsilon == pytest.approx(4.0 * before.upsilon)
    rejected = [h for h in hist if not h.accepted]
    assert rejected, "from (-1.2, 1) some trial steps are too long and must be rejected"
    # near the solution the damping mu_k = upsilon_k * ||F_k|| vanishes with the residual
    assert hist[-1].mu < 1e-6 * hist[0].mu


def test_powell_singular_function_converges_to_the_singular_root() -> None:
    res = improved_lm(powell_singular, powell_singular_jac, np.array([3.0, -1.0, 0.0, 1.0]))
    assert np.linalg.norm(res.x) < 1e-5
    assert res.cost < 1e-20


@pytest.mark.parametrize(
    ("fun", "jac", "x0"),
    [
        (rosenbrock, rosenbrock_jac, np.array([-1.2, 1.0])),
        (osborne1, osborne1_jac, np.array([0.5, 1.5, -1.0, 0.01, 0.02])),
    ],
)
def test_final_cost_matches_scipy_least_squares(fun, jac, x0) -> None:  # type: ignore[no-untyped-def]
    ours = improved_lm(fun, jac, x0)
    ref = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert ours.converged
    assert ours.cost == pytest.approx(ref.cost, rel=1e-8, abs=1e-20)


def test_osborne1_nonzero_residual_reaches_the_published_minimum() -> None:
    res = improved_lm(osborne1, osborne1_jac, np.array([0.5, 1.5, -1.0, 0.01, 0.02]))
    # MGH: f = 5.46489e-5 = ||F||² at the minimum
    assert 2.0 * res.cost == pytest.approx(5.46489e-5, rel=1e-5)
    assert res.reason in ("ftol", "gtol", "xtol")


def test_linear_problem_is_solved_exactly() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(40, 6))
    b = rng.normal(size=40)
    ref = np.linalg.lstsq(a, b, rcond=None)[0]
    ref_cost = 0.5 * float(np.sum((a @ ref - b) ** 2))
    res = improved_lm(lambda x: a @ x - b, lambda x: a, np.zeros(6))
    assert res.converged and res.reason in ("ftol", "gtol", "no_reduction")
    assert res.cost == pytest.approx(ref_cost, rel=1e-12)
    np.testing.assert_allclose(res.x, ref, rtol=1e-6, atol=1e-12)


def test_jac_scaling_makes_badly_scaled_columns_harmless() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(size=(30, 4)) * np.array([1e-4, 1.0, 1e3, 1e6])
    x_true = np.array([2e3, -1.0, 3e-3, 4e-7])
    b = a @ x_true
    res = improved_lm(lambda x: a @ x - b, lambda x: a, np.zeros(4), x_scale="jac")
    np.testing.assert_allclose(res.x, x_true, rtol=1e-8)


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="p0 < p1 < p2"):
        improved_lm(rosenbrock, rosenbrock_jac, np.zeros(2), p0=0.5, p1=0.25)
    with pytest.raises(ValueError, match="upsilon1 > m"):
        improved_lm(rosenbrock, rosenbrock_jac, np.zeros(2), upsilon1=1e-9, m=1e-8)
    with pytest.raises(ValueError, match="x_scale"):
        improved_lm(rosenbrock, rosenbrock_jac, np.zeros(2), x_scale=np.array([1.0, -1.0]))


def test_stops_at_max_iter_when_told() -> None:
    res = improved_lm(powell_singular, powell_singular_jac, np.array([3.0, -1.0, 0.0, 1.0]), max_iter=3)
    assert res.iterations == 3
    assert not res.converged
    assert res.reason == "max_iter"


def test_a_converged_point_stops_at_its_jacobian_without_evaluating_the_steps(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A nearly linear problem (the calibrations): the second iteration's LM step predicts nothing
    left to gain, so the iteration stops there (``ftol``) instead of evaluating its three steps,
    at the same point to the model's accuracy."""
    rng = np.random.default_rng(5)
    a = rng.normal(size=(300, 8))
    b = rng.normal(size=300)

    def f(x: Vec) -> Vec:
        return a @ x + 1e-5 * np.sin(3.0 * x).sum() - b

    def j(x: Vec) -> Vec:
        return a + 3e-5 * np.cos(3.0 * x)[None, :]

    fast = improved_lm(f, j, np.zeros(8), x_scale="jac")
    pred_ftol = lm.PRED_FTOL
    monkeypatch.setattr(lm, "PRED_FTOL", 0.0)
    slow = improved_lm(f, j, np.zeros(8), x_scale="jac")
    assert fast.reason == "ftol" and slow.reason == "ftol"
    assert (fast.n_residual_evals, slow.n_residual_evals) == (4, 7)
    assert fast.history[-1].accepted is False and np.isnan(fast.history[-1].ratio)
    assert fast.cost - slow.cost <= pred_ftol * slow.cost
    # a step the test leaves out moves the fitted values by less than sqrt(PRED_FTOL)·||F||
    bound = np.sqrt(pred_ftol * 2.0 * slow.cost)
    assert 0.0 < np.max(np.abs(a @ fast.x - a @ slow.x)) < bound


def test_a_jacobian_at_the_start_is_used_instead_of_a_first_evaluation() -> None:
    x0 = np.array([0.5, 1.5, -1.0, 0.01, 0.02])
    plain = improved_lm(osborne1, osborne1_jac, x0)
    given = improved_lm(osborne1, osborne1_jac, x0, jacobian_x0=osborne1_jac(x0))
    assert given.n_jacobian_evals == plain.n_jacobian_evals - 1
    np.testing.assert_array_equal(given.x, plain.x)
    with pytest.raises(ValueError, match="jacobian_x0 must have shape"):
        improved_lm(osborne1, osborne1_jac, x0, jacobian_x0=np.zeros((3, 5)))
    last = improved_lm(osborne1, osborne1_jac, x0, jacobian_at_solution=False)
    np.testing.assert_array_equal(last.x, plain.x)
    assert last.n_jacobian_evals <= plain.n_jacobian_evals


def test_damping_factor_rule_of_step_7() -> None:
    rule = dict(m=1e-8, p1=0.25, p2=0.75)
    assert lm.next_upsilon(1e-4, 0.1, **rule) == 4e-4  # poorly predicted: more damping
    assert lm.next_upsilon(1e-4, -np.inf, **rule) == 4e-4  # a non-finite trial cost counts as poor
    assert lm.next_upsilon(1e-4, 0.25, **rule) == 1e-4  # p1 ≤ r ≤ p2: unchanged, bounds included
    assert lm.next_upsilon(1e-4, 0.75, **rule) == 1e-4
    assert lm.next_upsilon(1e-4, 0.9, **rule) == 2.5e-5  # well predicted: less damping
    assert lm.next_upsilon(2e-8, 0.9, **rule) == 1e-8  # but never below m
