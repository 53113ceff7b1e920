"""The variogram fits solved together (``variogram.FIT_METHOD = "batch"``, the default) change
nothing a user sees: the kriging kinds choose the same direction separation, the same per-joint
weights from the same candidates, keep and drop the same parts and predict the check rows to 1e-6 mm
as with every fit solved on its own (``"each"``), on several campaigns."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_fast_fits import CAMPAIGNS, _fit_and_check, campaigns  # noqa: F401 (campaigns: a fixture)

from comp_daemon.estimation import variogram
from comp_daemon.models.kriging import KrigingFit, fit_kriging
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot

MODELS = ("kriging:aniso", "kriging-backlash")  # the per-joint weight search; the direction grid


@pytest.mark.parametrize("name", sorted(CAMPAIGNS))
def test_batched_variogram_fits_keep_every_kriging_kinds_choice(
    name: str,
    campaigns: dict[str, Path],  # noqa: F811 (the fixture imported above)
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    robot = CAMPAIGNS[name][1]
    batch = {m: _fit_and_check(campaigns[name], robot, m) for m in MODELS}
    with monkeypatch.context() as m:
        m.setattr(variogram, "FIT_METHOD", "each")
        each = {model: _fit_and_check(campaigns[name], robot, model) for model in MODELS}
    for model in MODELS:
        got, ref = batch[model]["info"], each[model]["info"]
        assert got["selection"]["kept"] == ref["selection"]["kept"], model
        assert got["selection"]["dropped"] == ref["selection"]["dropped"], model
        for key in ("joint_weights", "direction_separation_deg"):
            assert got.get(key) == ref.get(key), (model, key)
        assert batch[model]["check_rms"] == pytest.approx(each[model]["check_rms"], abs=1e-6)
        np.testing.assert_allclose(batch[model]["pred"], each[model]["pred"], rtol=0.0, atol=1e-6)


def _joint_one_field(n: int, seed: int) -> tuple[NominalModel, np.ndarray, np.ndarray]:
    """An error field of joint 1 alone: the per-joint weights the search finds are kept."""
    kr = load_robot("kr210")
    lim = kr.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    a = mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 90.0)
    nominal = NominalModel(kr)
    s = np.sin(np.deg2rad(a[:, 0]) * 6.0)
    field = 0.05 * np.stack([s, np.cos(np.deg2rad(a[:, 0]) * 6.0), s], axis=1)
    p = nominal.predict_tcp_mm(a) + field + np.random.default_rng(seed + 1).normal(size=(n, 3)) * 0.002
    return nominal, a, p


def test_the_per_joint_weight_search_sees_the_same_candidates(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every joint weighting the search tries gets the same leave-one-out RMS (to 1e-9 mm) with the
    batched fits; the same weights win and are kept by the same held-out judgement."""
    nominal, a, p = _joint_one_field(300, 2)

    def fit() -> KrigingFit:
        return fit_kriging(nominal, a, p, direction="blind", anisotropic=True)

    batch = fit()
    monkeypatch.setattr(variogram, "FIT_METHOD", "each")
    each = fit()
    assert len(batch.weight_candidates) == len(each.weight_candidates) > 6
    for (w_b, loo_b), (w_e, loo_e) in zip(batch.weight_candidates, each.weight_candidates, strict=True):
        assert w_b == w_e
        assert loo_b == pytest.approx(loo_e, abs=1e-9)
    np.testing.assert_array_equal(batch.model.metric.joint_weights, each.model.metric.joint_weights)
    assert batch.anisotropic_decision is not None and each.anisotropic_decision is not None
    assert batch.anisotropic_decision.kept and each.anisotropic_decision.kept
    assert batch.loo_rms_mm == pytest.approx(each.loo_rms_mm, abs=1e-9)
    q = a[:50] + 1.5
    np.testing.assert_allclose(
        batch.model.predict_tcp_mm(q), each.model.predict_tcp_mm(q), rtol=0.0, atol=1e-6
    )
