"""Moth-flame optimisers (seed 002, spec A.7): update rules, same minimum as LM, ballbar and IK objectives."""

from __future__ import annotations

from typing import Literal

import numpy as np
import pytest

from comp_daemon.estimation.lm import improved_lm
from comp_daemon.estimation.mfo import at_bound, ballbar_objective, optimise, solve_ik_mfo
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, ballbar_lengths_mm, fit_ballbar
from comp_daemon.kinematics.poe import irb120_table1, poe_error_jacobian, poe_flange_pose, poe_tcp_position_mm
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")
MODEL = irb120_table1(ROBOT).with_tool((30.0, 20.0, 50.0))


def _sphere(pop: np.ndarray) -> np.ndarray:
    return np.sum(pop**2, axis=1)


@pytest.mark.parametrize("variant", ["mfo", "imfo", "woa"])
def test_update_rules_on_the_sphere(variant: Literal["mfo", "imfo", "woa"]) -> None:
    lb, ub = -10.0 * np.ones(10), 10.0 * np.ones(10)
    inside: list[bool] = []

    def watch(k: int, moths: np.ndarray) -> None:
        inside.append(bool(np.all((moths >= lb) & (moths <= ub))))

    res = optimise(_sphere, lb, ub, variant=variant, n_agents=30, max_iter=300, seed=0, callback=watch)
    assert res.iterations == 300 and res.evaluations == 300 * 30
    assert res.flame_numbers[0] == 30 and res.flame_numbers[-1] == 1
    assert np.all(np.diff(res.flame_numbers) <= 0)
    assert res.a_values[0] == pytest.approx(2.0 - 2.0 / 300) and res.a_values[-1] == pytest.approx(0.0)
    assert all(inside) and len(inside) == 300
    assert np.all(np.diff(res.best_history) <= 0.0)  # flames are elitist
    assert res.fun < 1e-3


def test_same_seed_same_run_and_target_stops_early() -> None:
    lb, ub = -5.0 * np.ones(4), 5.0 * np.ones(4)
    one = optimise(_sphere, lb, ub, n_agents=20, max_iter=100, seed=3)
    two = optimise(_sphere, lb, ub, n_agents=20, max_iter=100, seed=3)
    np.testing.assert_array_equal(one.x, two.x)
    stopped = optimise(_sphere, lb, ub, n_agents=20, max_iter=100, seed=3, target=1e-2)
    assert stopped.reached_at is not None and stopped.iterations == stopped.reached_at < 100
    assert stopped.fun < 1e-2


def test_reference_t_schedule_is_available() -> None:
    res = optimise(
        _sphere, -np.ones(5), np.ones(5), variant="mfo", t_mode="reference", n_agents=20, max_iter=100
    )
    assert res.fun < 1e-3


@pytest.mark.parametrize("variant", ["mfo", "imfo", "woa"])
def test_the_answer_is_the_best_point_ever_evaluated(variant: Literal["mfo", "imfo", "woa"]) -> None:
    """The flames are elitist: every evaluated moth competes, and none better is ever dropped."""
    seen: list[np.ndarray] = []

    def every_population(pop: np.ndarray) -> np.ndarray:
        seen.append(pop.copy())
        return _sphere(pop - 0.3)

    res = optimise(every_population, -np.ones(3), np.ones(3), variant=variant, n_agents=8, max_iter=25)
    values = np.concatenate([_sphere(pop - 0.3) for pop in seen])
    best = np.concatenate(seen)[int(np.argmin(values))]
    assert res.fun == values.min() and np.array_equal(res.x, best)
    running = np.minimum.accumulate([_sphere(pop - 0.3).min() for pop in seen])
    np.testing.assert_array_equal(res.best_history, running)


@pytest.mark.parametrize(
    ("options", "message"),
    [({"variant": "pso"}, "unknown variant 'pso'"), ({"t_mode": "papers"}, "unknown t_mode 'papers'")],
)
def test_an_unknown_variant_or_t_schedule_is_refused_before_any_evaluation(
    options: dict[str, str], message: str
) -> None:
    calls: list[int] = []

    def counted(pop: np.ndarray) -> np.ndarray:
        calls.append(pop.shape[0])
        return _sphere(pop)

    with pytest.raises(ValueError, match=message):
        optimise(counted, -np.ones(2), np.ones(2), n_agents=4, max_iter=3, target=np.inf, **options)  # type: ignore[arg-type]
    assert calls == []


def test_mfo_and_lm_reach_the_same_minimum() -> None:
    """Three POE errors from 20 noisy positions: a least-squares problem with one minimum in the box."""
    rng = np.random.default_rng(0)
    lim = ROBOT.axis_limits_deg
    a_deg = rng.uniform(lim[:, 0] / 2, lim[:, 1] / 2, (20, 6))
    free = np.array([2, 7, 8])  # dl3, dtheta2, dtheta3
    x_true = np.zeros(12)
    x_true[free] = [0.3, 0.002, -0.003]
    p_meas = poe_tcp_position_mm(MODEL, a_deg, x_true) + rng.normal(0.0, 0.01, (20, 3))

    def full(u: np.ndarray) -> np.ndarray:
        x = np.zeros((*np.shape(u)[:-1], 12))
        x[..., free] = u
        return x

    lm = improved_lm(
        lambda u: (poe_tcp_position_mm(MODEL, a_deg, full(u)) - p_meas).ravel(),
        lambda u: poe_error_jacobian(MODEL, a_deg, full(u)).reshape(-1, 12)[:, free],
        np.zeros(3),
        x_scale="jac",
        phi=1e-14,
    )

    def rms(pop: np.ndarray) -> np.ndarray:
        n = pop.shape[0]
        p = poe_tcp_position_mm(MODEL, np.tile(a_deg, (n, 1)), np.repeat(full(pop), 20, axis=0))
        return np.sqrt(np.mean(np.sum((p.reshape(n, 20, 3) - p_meas) ** 2, axis=2), axis=1))

    f_lm = float(rms(lm.x[None])[0])
    scale = np.array([1.0, 0.01, 0.01])
    for variant in ("mfo", "imfo"):
        res = optimise(rms, -scale, scale, variant=variant, n_agents=40, max_iter=300, seed=1)
        assert res.fun == pytest.approx(f_lm, rel=1e-8)
        assert np.all(np.abs(res.x - lm.x) / scale < 1e-5)


def test_ballbar_objective_is_the_rms_length_error() -> None:
    a_deg = np.random.default_rng(4).uniform(-30, 30, (25, 6)) + np.array([0, 0, 0, 0, 60, 0])
    truth = np.zeros(15)
    truth[[2, 7, 12]] = [0.2, 0.003, 0.5]
    bar = ballbar_lengths_mm(MODEL, a_deg, truth, PAPER_PIVOT_MM)
    fit = fit_ballbar(MODEL, a_deg, bar, PAPER_PIVOT_MM)
    free = fit.report.identifiable_index
    objective = ballbar_objective(MODEL, a_deg, bar, PAPER_PIVOT_MM, free)
    values = objective(np.vstack([np.zeros(free.size), fit.theta[free]]))
    assert values[0] == pytest.approx(fit.h_before_mm, rel=1e-12)
    assert values[1] == pytest.approx(fit.h_after_mm, abs=1e-12)


def test_ik_by_mfo_is_polished_and_checked() -> None:
    a_true = np.array([20.0, 10.0, 20.0, 30.0, 40.0, 50.0])
    pose = poe_flange_pose(MODEL, a_true[None])[0]
    p = poe_tcp_position_mm(MODEL, a_true[None])[0]
    box = np.column_stack([a_true - 30.0, a_true + 30.0])
    ik = solve_ik_mfo(MODEL, box, p, pose[:3, :3], n_agents=100, max_iter=100, seed=0)
    assert ik.ok and ik.position_error_mm < 1e-6
    np.testing.assert_allclose(ik.a_deg, a_true, atol=1e-6)
    # an unreachable target is reported, not returned as a solution
    far = solve_ik_mfo(
        MODEL, box, p + np.array([900.0, 0.0, 0.0]), pose[:3, :3], n_agents=30, max_iter=30, seed=0
    )
    assert not far.ok and far.position_error_mm > 100.0


def test_at_bound_flags_values_near_the_box() -> None:
    lb, ub = -np.ones(3), np.ones(3)
    np.testing.assert_array_equal(at_bound(np.array([0.0, 0.995, -0.999]), lb, ub), [False, True, True])
