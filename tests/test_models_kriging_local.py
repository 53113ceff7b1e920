"""Kriging in local neighbourhoods against the dense solution, and per-joint ranges."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.estimation.local_kriging import LocalKriging
from comp_daemon.estimation.variogram import VariogramModel
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.kriging import LOO_MAX_SAMPLES, KrigingModel, fit_kriging
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")


def _axes(n: int, seed: int, half_max: float = 60.0) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, half_max)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@pytest.fixture(scope="module")
def cyclic() -> dict[str, np.ndarray]:
    """A robot with geometric and cyclic transmission errors and backlash: 500 samples, 300 checks."""
    rng = np.random.default_rng(0)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros(2).with_values(
        ["c1_1", "c2_1", "s3_1", "c2_2", "s1_2", "h2"], [0.004, 0.003, 0.002, 0.002, 0.002, 0.003]
    )
    a, q = _axes(500, 1), _axes(300, 3)
    d, dq = rng.choice([-1.0, 1.0], (500, 6)), rng.choice([-1.0, 1.0], (300, 6))
    p = twin_tcp_mm(KR, truth, eff, a, d) + rng.normal(size=(500, 3)) * 0.005
    pq = twin_tcp_mm(KR, truth, eff, q, dq) + rng.normal(size=(300, 3)) * 0.005
    return {"a": a, "d": d, "p": p, "q": q, "dq": dq, "pq": pq}


def test_all_samples_as_neighbours_is_the_dense_solution(cyclic: dict[str, np.ndarray]) -> None:
    a, d, p, q, dq = (cyclic[k] for k in ("a", "d", "p", "q", "dq"))
    dense = fit_kriging(NominalModel(KR), a, p, dir=d, neighbours=None).model
    assert dense.neighbours is None and dense.metric.direction_aware
    local = KrigingModel(
        dense.base, dense.metric, a, d, dense.residual_mm, dense.variograms, neighbours=len(a)
    )
    q, dq = q[:60], dq[:60]  # each query solves a 501 × 501 system here
    r_dense, s_dense = dense.predict_residual_mm(q, dq, return_std=True)
    r_local, s_local = local.predict_residual_mm(q, dq, return_std=True)
    np.testing.assert_allclose(r_local, r_dense, rtol=0, atol=1e-9)
    np.testing.assert_allclose(s_local, s_dense, rtol=0, atol=1e-9)
    # leave-one-out on n − 1 neighbours is Dubrule's closed form of the dense system
    assert isinstance(local.kriging, LocalKriging)
    np.testing.assert_allclose(
        local.kriging.loo_residuals(np.arange(20)), dense.kriging.loo_residuals()[:20], rtol=0, atol=1e-9
    )


def test_fifty_neighbours_predict_close_to_the_dense_solution(cyclic: dict[str, np.ndarray]) -> None:
    a, d, p, q, dq, pq = (cyclic[k] for k in ("a", "d", "p", "q", "dq", "pq"))
    kf = calibrate_kinematic(KR, a, p, dir=d, effects=("ratio", "backlash"))
    dense = fit_kriging(kf.model, a, p, dir=d, neighbours=None)
    local = fit_kriging(kf.model, a, p, dir=d, neighbours=50)
    assert local.model.neighbours == 50
    e_base = _rms(pq - kf.model.predict_tcp_mm(q, dq))
    e_dense = _rms(pq - dense.model.predict_tcp_mm(q, dq))
    e_local = _rms(pq - local.model.predict_tcp_mm(q, dq))
    assert e_dense < 0.8 * e_base  # the kriging has something to predict
    assert e_local < 1.1 * e_dense
    gap = _rms(local.model.predict_tcp_mm(q, dq) - dense.model.predict_tcp_mm(q, dq))
    assert gap < 0.5 * (e_base - e_dense)


def test_large_sets_default_to_local_neighbourhoods() -> None:
    rng = np.random.default_rng(1)
    n = 2500
    a = _axes(n, 4)
    p = (
        NominalModel(KR).predict_tcp_mm(a)
        + 0.01 * np.sin(np.deg2rad(a[:, :3]) * 3)
        + rng.normal(size=(n, 3)) * 0.002
    )
    fit = fit_kriging(NominalModel(KR), a, p, direction="blind")
    assert fit.model.neighbours is not None
    assert fit.loo_samples == LOO_MAX_SAMPLES and fit.loo_rows.size == LOO_MAX_SAMPLES
    assert fit.loo_rms_mm < 0.5 * fit.base_rms_mm


def test_per_joint_ranges_find_the_joint_the_error_depends_on() -> None:
    """An error field of joint 1 alone: the anisotropic metric weights joint 1 above the others."""
    rng = np.random.default_rng(2)
    a, q = _axes(300, 5, 90.0), _axes(200, 6, 90.0)
    nominal = NominalModel(KR)

    def field(x: np.ndarray) -> np.ndarray:
        s = np.sin(np.deg2rad(x[:, 0]) * 6.0)
        return 0.05 * np.stack([s, np.cos(np.deg2rad(x[:, 0]) * 6.0), s], axis=1)

    p = nominal.predict_tcp_mm(a) + field(a) + rng.normal(size=(300, 3)) * 0.002
    pq = nominal.predict_tcp_mm(q) + field(q)
    iso = fit_kriging(nominal, a, p, direction="blind")
    aniso = fit_kriging(nominal, a, p, direction="blind", anisotropic=True)
    w = aniso.model.metric.joint_weights
    assert w[0] == np.max(w) and w[0] > np.min(w[1:])
    assert len(aniso.weight_candidates) > 6
    assert aniso.loo_rms_mm < 0.5 * iso.loo_rms_mm
    assert _rms(pq - aniso.model.predict_tcp_mm(q)) < 0.5 * _rms(pq - iso.model.predict_tcp_mm(q))


def test_shared_variogram_pairs_give_each_metric_its_own_empirical_variogram() -> None:
    """The pairs computed once give, for every metric tried, the semivariogram of the embedded states."""
    from comp_daemon.estimation.variogram import JointStatePairs, empirical_semivariogram
    from comp_daemon.models.kriging import JointStateMetric

    rng = np.random.default_rng(5)
    a = _axes(120, 6)
    d = rng.choice([-1.0, 0.0, 1.0], (120, 6))
    res = rng.normal(size=(120, 3))
    pairs = JointStatePairs(a, d, res)
    for metric in (
        JointStateMetric.blind(),
        JointStateMetric(np.array([1.0, 2.0, 0.5, 1.0, 1.0, 3.0]), np.full(6, 20.0)),
        JointStateMetric(dir_separation_deg=np.array([0.0, 5.0, 10.0, 0.0, 40.0, 80.0])),
    ):
        got = pairs.semivariogram(metric.joint_weights, metric.dir_separation_deg, 12, None)
        want = empirical_semivariogram(metric.embed(a, d), res)
        np.testing.assert_allclose(got.edges, want.edges, rtol=1e-12)
        np.testing.assert_array_equal(got.count, want.count)
        np.testing.assert_allclose(got.gamma, want.gamma, rtol=1e-10)
        np.testing.assert_allclose(got.lag, want.lag, rtol=1e-10)


def test_queries_of_another_dimension_are_refused() -> None:
    rng = np.random.default_rng(5)
    x, z = rng.uniform(-1.0, 1.0, (12, 4)), rng.normal(size=(12, 1))
    local = LocalKriging(x, z, (VariogramModel("exponential", 0.1, 1.0, 1.0),), neighbours=5)
    with pytest.raises(ValueError, match=r"query coordinates must be \(m, 4\), got \(2, 3\)"):
        local.predict(np.zeros((2, 3)))
    assert local.predict(np.zeros((2, 4))).shape == (2, 1)
