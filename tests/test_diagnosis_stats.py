"""Cross-validation from Gram matrices, folds of pose groups, the cluster-robust Wald test, 'where'."""

from __future__ import annotations

import numpy as np
import pytest
from diagnosis_campaigns import NOISE_FLOOR_MM, make_campaign

from comp_daemon.diagnosis import diagnose
from comp_daemon.diagnosis.fitting import predict_mm
from comp_daemon.diagnosis.stats import LinearProblem, make_folds
from comp_daemon.diagnosis.where import equivalent_joint_error_deg
from comp_daemon.models.effects import MassModel


def random_problem(rng: np.random.Generator, n: int = 120, m: int = 6, groups: int | None = None):
    jac = rng.normal(size=(n, 3, m)) * rng.uniform(0.1, 1000.0, m)
    resid = rng.normal(size=(n, 3))
    group = np.arange(n) if groups is None else rng.integers(0, groups, n)
    return jac, resid, group


def test_folds_keep_pose_groups_together_and_are_balanced() -> None:
    group = np.repeat(np.arange(50), np.random.default_rng(0).integers(1, 4, 50))
    fold = make_folds(group, 5, seed=1)
    for g in np.unique(group):
        assert len(np.unique(fold[group == g])) == 1
    per_fold = [len(np.unique(group[fold == f])) for f in range(5)]
    assert max(per_fold) - min(per_fold) <= 1
    assert np.array_equal(fold, make_folds(group, 5, seed=1))


def test_cv_error_from_gram_matrices_equals_brute_force_refits() -> None:
    rng = np.random.default_rng(2)
    jac, resid, group = random_problem(rng, groups=40)
    fold = make_folds(group, 4, seed=3)
    lp = LinearProblem(resid, jac, group, fold)
    cols = [0, 2, 3, 5]
    total = 0.0
    for f in range(4):
        train, test = fold != f, fold == f
        a = jac[train][:, :, cols].reshape(-1, len(cols))
        step, *_ = np.linalg.lstsq(a, resid[train].reshape(-1), rcond=None)
        err = resid[test] - jac[test][:, :, cols] @ step
        total += float(np.sum(err**2))
    assert lp.cv_sse(cols) == pytest.approx(total, rel=1e-9)
    assert lp.cv_rms_mm(cols) == pytest.approx(np.sqrt(total / len(resid)), rel=1e-9)
    full = jac[:, :, cols].reshape(-1, len(cols))
    step, *_ = np.linalg.lstsq(full, resid.reshape(-1), rcond=None)
    assert lp.sse(cols) == pytest.approx(float(np.sum((resid.reshape(-1) - full @ step) ** 2)), rel=1e-9)


def test_wald_p_values_are_uniform_under_the_null_and_small_under_the_alternative() -> None:
    rng = np.random.default_rng(4)
    p_null, p_alt = [], []
    for _ in range(300):
        jac, _, group = random_problem(rng, n=150, m=5)
        noise = rng.normal(size=(150, 3)) * rng.uniform(0.5, 2.0, (150, 1))  # heteroscedastic by pose
        fold = make_folds(group, 5, seed=0)
        lp = LinearProblem(noise, jac, group, fold)
        p_null.append(lp.wald([0, 1, 2, 3, 4], [4]).p_value)
        signal = noise + 0.5 * jac[:, :, 4] / np.linalg.norm(jac[:, :, 4]) * np.sqrt(450)
        p_alt.append(LinearProblem(signal, jac, group, fold).wald([0, 1, 2, 3, 4], [4]).p_value)
    p_null_arr = np.array(p_null)
    assert 0.02 < np.mean(p_null_arr < 0.05) < 0.09
    assert 0.4 < np.mean(p_null_arr < 0.5) < 0.6
    assert np.mean(np.array(p_alt) < 0.001) > 0.9


def test_wald_tests_the_parameter_value_not_the_step_from_it() -> None:
    rng = np.random.default_rng(5)
    jac, noise, group = random_problem(rng, n=100, m=3)
    fold = make_folds(group, 5, seed=0)
    value = np.array([0.0, 0.0, 0.5 / np.linalg.norm(jac[:, :, 2])])
    # linearised at the optimum: the residual is noise only, the parameter is far from zero
    lp = LinearProblem(noise, jac, group, fold)
    at_zero = lp.wald([0, 1, 2], [2], at=np.zeros(3))
    assert at_zero.statistic == lp.wald([0, 1, 2], [2]).statistic
    assert lp.wald([0, 1, 2], [2], at=value * 100).p_value < 1e-6 < at_zero.p_value


def test_equivalent_joint_error_recovers_a_single_joint_angle_error() -> None:
    rng = np.random.default_rng(6)
    jac_theta = rng.normal(size=(20, 3, 6)) * 1000.0
    delta_rad = rng.normal(size=20) * 1e-5
    resid = jac_theta[:, :, 2] * delta_rad[:, None]
    e = equivalent_joint_error_deg(resid, jac_theta)
    assert np.allclose(e[:, 2], np.rad2deg(delta_rad), rtol=1e-12, atol=0)
    jac_theta[:, :, 5] = 0.0
    assert np.isnan(equivalent_joint_error_deg(resid, jac_theta)[:, 5]).all()


def test_where_breakdown_matches_the_post_geometric_residual() -> None:
    camp = make_campaign("kr210", 61, [("backlash", 2, 8 * NOISE_FLOOR_MM)])
    diag = diagnose(camp.dataset, camp.robot)
    where = diag.where
    geo = diag.steps[0].fit
    resid = diag.obs.xyz_mm - predict_mm(MassModel.from_robot(camp.robot), geo.params, geo.effects, diag.obs)
    for k, ax in enumerate("xyz"):
        assert where["axis_rms_mm"][ax] == pytest.approx(np.sqrt(np.mean(resid[:, k] ** 2)), rel=1e-3)
    assert sum(r["n"] for r in where["regions"]) == len(camp.dataset)
    joint2 = where["per_joint"][1]
    assert joint2["share_pct"] == max(p["share_pct"] for p in where["per_joint"])
    assert joint2["share_pct"] > 80
    # the equivalent error of joint 2 steps with the approach direction like 2·h
    h = camp.effects.backlash_deg[1]
    assert np.sign(joint2["vs_dir"]["step_deg"]) == np.sign(h)
    assert abs(joint2["vs_dir"]["step_deg"]) == pytest.approx(2 * abs(h), rel=0.5)
    assert sum(b["n"] for b in joint2["vs_angle"]) == len(camp.dataset)
