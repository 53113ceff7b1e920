"""Ordinary kriging (seed 001 eqs 18–28): exactness, unbiasedness, the Lagrange system, LOO, variance."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.estimation.variogram import VariogramModel, pairwise_distances
from comp_daemon.models.kriging import OrdinaryKriging


def _field(seed: int, n: int = 60, d: int = 4, k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-50.0, 50.0, (n, d))
    z = np.stack(
        [np.sin(x[:, 0] / 20.0 + c) + 0.3 * np.cos(x[:, 1] / 15.0) * (c + 1) for c in range(k)], axis=1
    )
    return x, z


VGS = (
    VariogramModel("exponential", 0.0, 1.0, 60.0),
    VariogramModel("gaussian", 0.0, 0.8, 40.0),
    VariogramModel("exponential", 0.0, 2.0, 90.0),
)


def test_kriging_interpolates_the_samples_exactly_without_nugget() -> None:
    x, z = _field(0)
    ok = OrdinaryKriging(x, z, VGS)
    pred = ok.predict(x)
    assert isinstance(pred, np.ndarray)
    np.testing.assert_allclose(pred, z, atol=1e-7 * np.abs(z).max())


def test_weights_sum_to_one_and_reproduce_the_prediction() -> None:
    x, z = _field(1)
    ok = OrdinaryKriging(x, z, VGS)
    q = np.random.default_rng(5).uniform(-70.0, 70.0, (25, x.shape[1]))  # inside and outside the hull
    pred = ok.predict(q)
    assert isinstance(pred, np.ndarray)
    for c in range(3):
        w = ok.weights(q, c)
        assert w.shape == (25, x.shape[0])
        np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-10)
        np.testing.assert_allclose(w @ z[:, c], pred[:, c], atol=1e-9)
    # at a sample the weights pick that sample alone
    w0 = ok.weights(x[:3], 0)
    np.testing.assert_allclose(w0, np.eye(x.shape[0])[:3], atol=1e-8)


def test_weights_solve_the_bordered_lagrange_system() -> None:
    """[R 1; 1ᵀ 0][λ; −μ] = [r; 1] (eqs 25–26), solved independently with a dense solver."""
    x, z = _field(2, n=30)
    vg = VGS[0]
    ok = OrdinaryKriging(x, z[:, :1], (vg,))
    q = np.array([[3.0, -7.0, 11.0, 0.5]])
    n = x.shape[0]
    big = np.ones((n + 1, n + 1))
    big[:n, :n] = vg.correlation(pairwise_distances(x))
    big[n, n] = 0.0
    rhs = np.append(vg.correlation(pairwise_distances(q, x))[0], 1.0)
    sol = np.linalg.solve(big, rhs)
    np.testing.assert_allclose(ok.weights(q, 0)[0], sol[:n], atol=1e-10)


def test_variance_is_the_papers_mse_at_the_optimal_weights_and_zero_at_samples() -> None:
    x, z = _field(3, n=40)
    vg = VGS[1]
    ok = OrdinaryKriging(x, z[:, :1], (vg,))
    q = np.random.default_rng(2).uniform(-50.0, 50.0, (6, x.shape[1]))
    _, std = ok.predict(q, return_std=True)
    big_r = vg.correlation(pairwise_distances(x))
    r = vg.correlation(pairwise_distances(q, x))
    w = ok.weights(q, 0)
    mse = vg.psill * (
        1.0 + np.einsum("mi,ij,mj->m", w, big_r, w) - 2.0 * np.einsum("mi,mi->m", w, r)
    )  # eq. 24
    np.testing.assert_allclose(std[:, 0] ** 2, mse, rtol=1e-6, atol=1e-12)
    # any other unbiased weights do worse (minimum variance)
    rng = np.random.default_rng(9)
    for _ in range(5):
        other = w + rng.normal(0.0, 0.01, w.shape)
        other -= (other.sum(axis=1, keepdims=True) - 1.0) / other.shape[1]
        mse_other = vg.psill * (
            1.0 + np.einsum("mi,ij,mj->m", other, big_r, other) - 2.0 * np.einsum("mi,mi->m", other, r)
        )
        assert np.all(mse_other >= mse - 1e-12)
    _, std_at = ok.predict(x[:5], return_std=True)
    assert np.all(std_at < 1e-5)


def test_leave_one_out_closed_form_equals_refitting() -> None:
    x, z = _field(4, n=25)
    vgs = (VariogramModel("exponential", 0.05, 1.0, 60.0), VGS[1], VGS[2])
    ok = OrdinaryKriging(x, z, vgs)
    loo = ok.loo_residuals()
    for i in (0, 7, 24):
        keep = np.arange(x.shape[0]) != i
        pred = OrdinaryKriging(x[keep], z[keep], vgs).predict(x[i : i + 1])
        assert isinstance(pred, np.ndarray)
        np.testing.assert_allclose(loo[i], z[i] - pred[0], atol=1e-8)


def test_nugget_smooths_instead_of_interpolating() -> None:
    x, z = _field(5)
    noisy = z[:, :1] + np.random.default_rng(0).normal(0.0, 0.1, (x.shape[0], 1))
    ok = OrdinaryKriging(x, noisy, (VariogramModel("exponential", 0.01, 1.0, 60.0),))
    pred = ok.predict(x)
    assert isinstance(pred, np.ndarray)
    assert np.abs(pred - noisy).max() > 1e-3
    np.testing.assert_allclose(ok.weights(x[:4], 0).sum(axis=1), 1.0, atol=1e-10)


def test_batch_equals_single_queries() -> None:
    x, z = _field(6)
    ok = OrdinaryKriging(x, z, VGS)
    q = np.random.default_rng(1).uniform(-50.0, 50.0, (8, x.shape[1]))
    batch = ok.predict(q)
    assert isinstance(batch, np.ndarray)
    for i in range(8):
        single = ok.predict(q[i : i + 1])
        assert isinstance(single, np.ndarray)
        np.testing.assert_allclose(single[0], batch[i], rtol=1e-12, atol=1e-12)


def test_duplicate_samples_without_nugget_are_refused_by_name() -> None:
    x, z = _field(7, n=10)
    x[6] = x[2]
    with pytest.raises(ValueError, match=r"samples 3 and 7 are the same joint state"):
        OrdinaryKriging(x, z[:, :1], (VariogramModel("exponential", 0.0, 1.0, 60.0),))
    # with a nugget the same data are fine
    OrdinaryKriging(x, z[:, :1], (VariogramModel("exponential", 0.1, 1.0, 60.0),))


def test_bad_shapes_are_refused() -> None:
    x, z = _field(8, n=10)
    with pytest.raises(ValueError, match="same n"):
        OrdinaryKriging(x[:9], z, VGS)
    with pytest.raises(ValueError, match="3 components but 1 variograms"):
        OrdinaryKriging(x, z, VGS[:1])
    ok = OrdinaryKriging(x, z, VGS)
    with pytest.raises(ValueError, match=r"query coordinates must be \(m, 4\)"):
        ok.predict(np.zeros((2, 3)))
