"""Semivariograms (seed 001 eq. 12): the estimator, the fitted models, and error similarity with backlash."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Literal

import numpy as np
import pytest

from comp_daemon.estimation.variogram import (
    VariogramModel,
    empirical_semivariogram,
    fit_variogram,
    pairwise_distances,
    valid_models,
)
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kriging import JointStateMetric, joint_space_semivariogram
from comp_daemon.robot.description import load_robot


def test_empirical_semivariogram_is_equation_12() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 10.0, (30, 2))
    z = rng.normal(size=(30, 2))
    emp = empirical_semivariogram(x, z, n_bins=5, max_lag=8.0)
    d = pairwise_distances(x)
    for b in range(5):
        lo, hi = emp.edges[b], emp.edges[b + 1]
        pairs = [
            (i, j)
            for i in range(30)
            for j in range(i + 1, 30)
            if (lo < d[i, j] <= hi) or (b == 0 and d[i, j] == 0)
        ]
        assert emp.count[b] == len(pairs)
        for c in range(2):
            expect = sum((z[i, c] - z[j, c]) ** 2 for i, j in pairs) / (2 * len(pairs))
            assert emp.gamma[b, c] == pytest.approx(expect, rel=1e-12)
        assert emp.lag[b] == pytest.approx(np.mean([d[i, j] for i, j in pairs]), rel=1e-12)


def test_default_bins_cover_half_the_largest_distance() -> None:
    x = np.arange(20.0)[:, None]
    emp = empirical_semivariogram(x, np.sin(x[:, 0]))
    assert len(emp.lag) == 12
    assert emp.edges[-1] == pytest.approx(9.5)
    full = empirical_semivariogram(x, np.sin(x[:, 0]), max_lag=np.inf)
    assert full.edges[-1] == pytest.approx(19.0)


@pytest.mark.parametrize(
    ("kind", "nugget"),
    [("spherical", 0.0), ("exponential", 0.0), ("gaussian", 0.0), ("exponential", 1.0), ("spherical", 1.0)],
)
def test_fit_recovers_a_known_range_and_sill(kind: str, nugget: float) -> None:
    """Gaussian random fields with a known covariance (8 realisations at 800 points), fitted back."""
    rng = np.random.default_rng(3)
    n = 800
    x = rng.uniform(0.0, 200.0, (n, 2))
    true = VariogramModel(kind, nugget, 4.0, 25.0)
    cov = true.psill * true.correlation(pairwise_distances(x)) + (nugget + 1e-8) * np.eye(n)
    z = np.linalg.cholesky(cov) @ rng.standard_normal((n, 8))
    emp = empirical_semivariogram(x, z, n_bins=20, max_lag=60.0)
    pooled = dataclasses.replace(emp, gamma=emp.gamma.mean(axis=1, keepdims=True))
    fitted = fit_variogram(pooled, kind=kind, dim=2, nugget=nugget > 0.0)
    assert fitted.kind == kind
    assert fitted.sill == pytest.approx(true.sill, rel=0.1)
    assert fitted.range == pytest.approx(true.range, rel=0.15)
    assert fitted.nugget == pytest.approx(nugget, abs=0.35)


def test_auto_picks_the_generating_model_and_spherical_is_refused_in_joint_space() -> None:
    rng = np.random.default_rng(4)
    x = rng.uniform(0.0, 200.0, (700, 2))
    true = VariogramModel("gaussian", 0.0, 2.0, 30.0)
    z = np.linalg.cholesky(true.psill * true.correlation(pairwise_distances(x)) + 1e-8 * np.eye(700)) @ (
        rng.standard_normal(700)
    )
    emp = empirical_semivariogram(x, z, max_lag=90.0)
    assert fit_variogram(emp, dim=2).kind == "gaussian"
    assert valid_models(6) == ("exponential", "gaussian")
    with pytest.raises(ValueError, match="spherical model is not a valid variogram in 6 dimensions"):
        fit_variogram(emp, kind="spherical", dim=6)


def test_model_values_and_round_trip() -> None:
    for kind in ("spherical", "exponential", "gaussian"):
        vg = VariogramModel(kind, 0.5, 2.0, 10.0)
        h = np.array([0.0, 1e-9, 5.0, 10.0, 1e4])
        g = vg.gamma(h)
        assert g[0] == 0.0
        assert g[1] == pytest.approx(0.5, abs=1e-6)  # the nugget right after 0
        assert g[-1] == pytest.approx(2.5, rel=1e-9)  # the sill far away
        assert np.all(np.diff(g) >= 0.0)
        assert VariogramModel.from_dict(vg.to_dict()) == vg
    with pytest.raises(ValueError, match="partial sill must be > 0"):
        VariogramModel("gaussian", 0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="unknown"):
        VariogramModel("cubic", 0.0, 1.0, 1.0)


def _joint_box(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo = np.array([-30.0, -110.0, 90.0, -60.0, -90.0, -90.0])
    hi = np.array([30.0, -60.0, 150.0, 60.0, -20.0, 90.0])
    a = lo + rng.random((n, 6)) * (hi - lo)
    d = rng.choice([-1.0, 1.0], (n, 6))
    return a, d


def test_backlash_errors_are_not_similar_in_joint_space_but_are_with_direction() -> None:
    """Seed 001 Figs 3–4: geometric errors are similar at small joint distances, backlash errors
    (random approach directions) are not — unless the distance includes the direction."""
    robot = load_robot("kr210")
    nominal = KinematicParams.from_robot(robot)
    a, d = _joint_box(500, 1)
    rng = np.random.default_rng(2)
    dx = np.zeros(N_PARAMS)
    dx[:30] = rng.normal(0.0, 1.0, 30) * np.tile([np.deg2rad(0.01), 0.2, 0.2, np.deg2rad(0.01), 0.0], 6)
    zero = EffectParams.zeros()
    p_nom = twin_tcp_mm(robot, nominal, zero, a)
    e_geo = twin_tcp_mm(robot, nominal.apply(dx), zero, a) - p_nom
    e_bl = twin_tcp_mm(robot, nominal, EffectParams(backlash_deg=np.full(6, 0.005)), a, d) - p_nom

    def small_lag_ratio(err: np.ndarray, metric: JointStateMetric) -> float:
        """γ (three axes summed) at the shortest lag with 50 pairs, over the error's variance (the sill)."""
        emp = joint_space_semivariogram(a, err, d, metric)
        k = int(np.argmax(emp.count >= 50))
        return float(np.sum(emp.gamma[k]) / np.sum(err.var(axis=0)))

    blind = JointStateMetric.blind()
    aware = JointStateMetric(dir_separation_deg=np.full(6, 40.0))
    assert small_lag_ratio(e_geo, blind) < 0.15  # similar: γ small at small joint distance
    assert small_lag_ratio(e_bl, blind) > 0.85  # no similarity: γ at the sill already
    assert small_lag_ratio(e_bl, aware) < 0.3  # similar again once the direction is in the distance


@pytest.mark.parametrize("kind", ["spherical", "exponential", "gaussian"])
def test_range_derivative_of_the_correlation_is_exact(kind: str) -> None:
    """The fit's analytic Jacobian rests on ∂ρ/∂a; against central differences."""
    from comp_daemon.estimation.variogram import _correlation, _correlation_da

    h = np.linspace(0.0, 30.0, 61)
    a, eps = 17.0, 1e-6
    rho = _correlation(kind, h, a)
    numeric = (_correlation(kind, h, a + eps) - _correlation(kind, h, a - eps)) / (2 * eps)
    np.testing.assert_allclose(_correlation_da(kind, h, a, rho), numeric, atol=1e-8)


def test_the_variogram_solver_is_scipys_trust_region_reflective_method(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Every fit of :func:`fit_variogram` one by one (``method="each"``) solves its bounded problem
    with ``bounded_lsq.trf_fit``;
    SciPy's ``least_squares(method="trf", x_scale="jac")`` finds the same point and cost on each,
    on fields with and without structure, both weightings, with and without a nugget, and the
    starts that end on a bound (the reflective steps) among them."""
    from scipy.optimize import least_squares

    from comp_daemon.estimation import variogram
    from comp_daemon.estimation.bounded_lsq import trf_fit

    seen = {"calls": 0, "on_bound": 0}

    def compared(fun: Any, jac: Any, x0: Any, lb: Any, ub: Any) -> tuple[np.ndarray, float]:
        x, cost = trf_fit(fun, jac, x0, lb, ub)
        ref = least_squares(fun, x0, jac=jac, bounds=(lb, ub), method="trf", x_scale="jac")
        np.testing.assert_allclose(x, ref.x, rtol=1e-12, atol=0.0)
        assert cost == pytest.approx(float(ref.cost), rel=1e-12, abs=1e-300)
        seen["calls"] += 1
        near = np.minimum(x - lb, ub - x) <= 1e-6 * (ub - lb)
        seen["on_bound"] += int(np.any(near))
        return x, cost

    monkeypatch.setattr(variogram, "trf_fit", compared)
    rng = np.random.default_rng(11)
    for trial in range(12):
        x = rng.uniform(0.0, 100.0, (60, 3))
        smooth = np.sin(x[:, :1] / rng.uniform(5.0, 40.0)) + np.cos(x[:, 1:2] / rng.uniform(5.0, 40.0))
        z = smooth * (trial % 3) + rng.normal(0.0, 0.3, (60, 1))
        emp = empirical_semivariogram(x, z, n_bins=int(rng.integers(5, 14)))
        weighting: Literal["cressie", "npairs"] = "cressie" if trial % 2 else "npairs"
        fit_variogram(emp, kind="auto", nugget=trial % 4 != 3, weighting=weighting, method="each")
    assert seen["calls"] == 12 * 3 * 4  # three kinds, four starting ranges each
    assert seen["on_bound"] > 0


def test_the_bounded_solver_refuses_what_it_cannot_solve() -> None:
    from comp_daemon.estimation.bounded_lsq import trf_fit

    def fun(p: np.ndarray) -> np.ndarray:
        return np.array([p[0] - 1.0, p[1] + 2.0, p[0] * p[1]])

    def jac(p: np.ndarray) -> np.ndarray:
        return np.array([[1.0, 0.0], [0.0, 1.0], [p[1], p[0]]])

    lo, hi = np.array([0.0, -1.0]), np.array([2.0, 1.0])
    with pytest.raises(ValueError, match="finite bounds"):
        trf_fit(fun, jac, np.zeros(2), np.array([0.0, -np.inf]), hi)
    with pytest.raises(ValueError, match="outside of the bounds"):
        trf_fit(fun, jac, np.array([3.0, 0.0]), lo, hi)
    with pytest.raises(ValueError, match="lower bound must be below"):
        trf_fit(fun, jac, np.zeros(2), hi, lo)
    x, _ = trf_fit(fun, jac, np.array([0.5, 0.5]), lo, hi)
    assert x[1] == pytest.approx(-1.0, abs=1e-6)  # on its bound


def _decaying(h: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p[:, :1] + p[:, 1:2] * (1.0 - np.exp(-h / p[:, 2:3]))


def _one_of_batch(fun: Any, jac: Any, i: int, m: int, p: np.ndarray, *, jacobian: bool = False) -> np.ndarray:
    """Problem ``i`` of a batch on its own: its ``m`` residuals (or Jacobian rows) at ``p``."""
    return (jac if jacobian else fun)(p[None, :], np.array([i]))[0, :m]


def test_the_batch_solver_is_the_single_solver_on_each_problem() -> None:
    """:func:`trf_fit_batch` on many bounded problems at once (different residual counts, padded;
    some ending on a bound) finds the point and cost :func:`trf_fit` finds on each alone."""
    from comp_daemon.estimation.bounded_lsq import trf_fit, trf_fit_batch

    rng = np.random.default_rng(4)
    n_problems, width = 40, 15
    m = rng.integers(5, width + 1, n_problems)
    h = np.sort(rng.uniform(0.5, 20.0, (n_problems, width)), axis=1)
    truth = np.stack(
        [
            rng.uniform(0.0, 0.3, n_problems),
            rng.uniform(0.5, 2.0, n_problems),
            rng.uniform(1.0, 8.0, n_problems),
        ],
        axis=1,
    )
    truth[::4, 0] = 0.0  # these end on the lower bound of the first parameter
    y = _decaying(h, truth) + rng.normal(0.0, 0.02, h.shape)
    weight = (np.arange(width)[None, :] < m[:, None]).astype(float)  # zero rows pad the short ones
    lb, ub = np.array([0.0, 0.01, 0.1]), np.array([1.0, 5.0, 30.0])
    x0 = np.tile([0.5, 1.0, 10.0], (n_problems, 1))

    def fun(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return weight[rows] * (_decaying(h[rows], p) - y[rows])

    def jac(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        e = np.exp(-h[rows] / p[:, 2:3])
        d = np.stack([np.ones_like(e), 1.0 - e, -p[:, 1:2] * e * h[rows] / p[:, 2:3] ** 2], axis=2)
        return weight[rows][:, :, None] * d

    x, cost = trf_fit_batch(fun, jac, x0, lb, ub, m)
    on_bound = 0
    for i in range(n_problems):
        alone = functools.partial(_one_of_batch, fun, jac, i, int(m[i]))
        xi, ci = trf_fit(alone, functools.partial(alone, jacobian=True), x0[i], lb, ub)
        np.testing.assert_allclose(x[i], xi, rtol=1e-8, atol=1e-12)
        assert cost[i] == pytest.approx(ci, rel=1e-10)
        on_bound += int(xi[0] < 1e-6)
    assert on_bound >= 5


def _weighted_cost(
    vg: VariogramModel, lag: np.ndarray, gam: np.ndarray, cnt: np.ndarray, weighting: str
) -> float:
    g = vg.gamma(lag)
    r = np.sqrt(cnt) * (gam / g - 1.0) if weighting == "cressie" else np.sqrt(cnt) * (g - gam) / gam.max()
    return 0.5 * float(r @ r)


def test_batched_variogram_fits_choose_as_the_fits_one_by_one() -> None:
    """Every component's problems solved together (``method="batch"``) end where the fits one by one
    end: the same weighted cost, and the same model wherever the bins determine it (a range below the
    first lag leaves the nugget and sill apart, and the range, free: any such model fits as well)."""
    from comp_daemon.estimation.variogram import fit_variograms

    rng = np.random.default_rng(3)
    compared = 0
    for trial in range(24):
        x = rng.uniform(0.0, 100.0, (100, 6))
        z = np.sin(x[:, :2] / rng.uniform(5.0, 40.0, 2)) @ rng.normal(size=(2, 3)) + rng.normal(
            0.0, 0.1, (100, 3)
        )
        emp = empirical_semivariogram(x, z, n_bins=int(rng.integers(6, 14)))
        if trial % 3 == 0:  # components with different non-empty bins: the batch pads the short ones
            emp = dataclasses.replace(emp, gamma=emp.gamma.copy())
            emp.gamma[-1, 1] = np.nan
        weighting = "cressie" if trial % 2 else "npairs"
        kw: dict[str, Any] = {"kind": "auto", "dim": 6, "nugget": trial % 4 != 3, "weighting": weighting}
        batch = fit_variograms([emp], method="batch", **kw)[0]
        each = fit_variograms([emp], method="each", **kw)[0]
        for c, (b, e) in enumerate(zip(batch, each, strict=True)):
            ok = np.isfinite(emp.gamma[:, c]) & (emp.count > 0)
            lag, gam, cnt = emp.lag[ok], emp.gamma[ok, c], emp.count[ok].astype(float)
            cost_b, cost_e = (_weighted_cost(v, lag, gam, cnt, weighting) for v in (b, e))
            assert cost_b == pytest.approx(cost_e, rel=1e-8)
            if min(b.range, e.range) > lag[0]:
                assert b.kind == e.kind
                np.testing.assert_allclose(b.gamma(lag), e.gamma(lag), rtol=1e-6)
                compared += 1
    assert compared >= 60
