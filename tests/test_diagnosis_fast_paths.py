"""The diagnosis's fast paths against their plain references.

* The remainder's structure test computes the out-of-fold shares of every permutation at once; a
  direct loop (bin means on each fold's training rows, predicted on its held-out rows) gives the
  same shares and the same decisions.
* A model's k fold solves are one batched call: each fold's least squares on the other folds.
* The further targets of a pose share one twin: the gravity torques carry the payload at the TCP
  whichever reflector is measured (as the Gauss–Newton cost has it), and the shared Jacobian is
  exact (central differences of the twin's predictions).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from diagnosis_campaigns import FURTHER_TARGETS_MM, random_geometry, sample_poses

from comp_daemon.diagnosis import structure
from comp_daemon.diagnosis.fitting import linearize_targets, predict_mm
from comp_daemon.diagnosis.stats import LinearProblem, make_folds
from comp_daemon.kinematics.params import N_PARAMS, TOOL_SLICE, KinematicParams
from comp_daemon.models.effects import EffectParams, MassModel, twin_state
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import load_robot


def _reference_shares(resid: np.ndarray, bins: np.ndarray, fold: np.ndarray) -> np.ndarray:
    """Out-of-fold share of the bin means, one permutation (row of ``bins``) at a time."""
    out = np.empty(len(bins))
    for p, row in enumerate(bins):
        sse = sst = 0.0
        for f in range(int(fold.max()) + 1):
            train, test = fold != f, fold == f
            mean_train = resid[train].mean(axis=0)
            pred = np.tile(mean_train, (int(test.sum()), 1))
            for b in np.unique(row[test]):
                in_train = train & (row == b)
                if in_train.any():
                    pred[row[test] == b] = resid[in_train].mean(axis=0)
            sse += float(np.sum((resid[test] - pred) ** 2))
            sst += float(np.sum((resid[test] - mean_train) ** 2))
        out[p] = 1.0 - sse / sst
    return out


def test_the_shares_of_every_permutation_at_once_are_the_direct_ones() -> None:
    rng = np.random.default_rng(3)
    n = 240
    resid = rng.normal(0.0, 0.01, (n, 3))
    resid[:, 1] += 0.004 * np.sin(np.linspace(0.0, 5.0, n))
    fold = make_folds(np.arange(n) // 2, 5, 0)  # pose groups of two rows
    rare = np.where(fold == 2, 3.0, rng.choice([0.0, 1.0, 2.0], n))  # a value only one fold holds
    for values in (np.linspace(0.0, 1.0, n), rng.choice([-1.0, 1.0], n), rare):
        b = structure._bins(values)
        perms = np.argsort(rng.random((structure._BLOCK + 40, n)), axis=1)  # more than one block
        bins = np.concatenate([b[None, :], b[perms]])
        fast = structure._oof_shares(resid, bins, fold)
        np.testing.assert_allclose(fast, _reference_shares(resid, bins, fold), rtol=0.0, atol=1e-12)


def test_the_structure_decisions_are_those_of_the_direct_shares(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three remainders (a step in time, a bump in an axis, noise): the same shares, p-values and
    verdicts with the direct computation."""
    for seed in range(3):
        rng = np.random.default_rng(40 + seed)
        n = 150
        cols: dict[str, np.ndarray | None] = {
            "t_s": np.sort(rng.uniform(0.0, 3600.0, n)),
            "a2": rng.uniform(-60.0, 60.0, n),
            "dir1": rng.choice([-1.0, 1.0], n),
        }
        resid = rng.normal(0.0, 0.01, (n, 3))
        if seed == 0:
            resid[np.asarray(cols["t_s"]) > 1800.0, 0] += 0.012
        if seed == 1:
            resid[:, 2] += 0.012 * np.cos(np.deg2rad(3.0 * np.asarray(cols["a2"])))
        fast = residual_structure_of(resid, cols)
        monkeypatch.setattr(structure, "_oof_shares", _reference_shares)
        direct = residual_structure_of(resid, cols)
        monkeypatch.undo()
        assert [(r.against, r.significant, r.p_value, r.permutations) for r in fast] == [
            (r.against, r.significant, r.p_value, r.permutations) for r in direct
        ]
        np.testing.assert_allclose([r.share_pct for r in fast], [r.share_pct for r in direct], atol=1e-9)
        assert any(r.significant for r in fast) == (seed < 2)


def residual_structure_of(
    resid: np.ndarray, cols: dict[str, np.ndarray | None]
) -> list[structure.StructureResult]:
    return structure.residual_structure(resid, cols, np.arange(len(resid)), folds=5, seed=7)


def _three_targets(payload_kg: float) -> tuple[MassModel, KinematicParams, EffectParams, MeasuredRows]:
    rng = np.random.default_rng(11)
    robot = load_robot("irb120")
    a, direction = sample_poses(robot, 40, rng)
    params = KinematicParams.from_robot(robot).apply(random_geometry(rng) * 0.3)
    effects = EffectParams.zeros(2).with_values(
        ["h2", "eps3", "c4_1", "s5_2", "C2", "C3", "kappa", "vx", "wz"],
        [0.01, 2e-4, 0.01, -0.01, 2e-5, 3e-5, 1.2e-5, 0.2, -0.1],
    )
    n = len(a)
    obs = MeasuredRows(
        a_deg=a,
        xyz_mm=np.zeros((n, 3)),
        dir=direction,
        payload_kg=np.full(n, payload_kg),
        temp_c=np.linspace(20.0, 26.0, n),
        pose_group=np.arange(n, dtype=np.int64),
        clock=np.linspace(0.0, 2.0, n),
        clock_name="t_s",
    )
    return (
        MassModel.from_robot(robot),
        params,
        effects,
        obs.stack_targets(np.zeros((n, 2, 3)), FURTHER_TARGETS_MM),
    )


def test_the_further_targets_carry_the_payload_at_the_tcp() -> None:
    """A pose's reflectors are measured at once, with the payload at the TCP: each further target is
    the TCP twin's flange carrying the target's place (old: the payload moved to the target)."""
    mass, params, effects, obs = _three_targets(payload_kg=3.0)
    n = len(obs) // 3
    tcp_rows = obs.take(np.arange(n))
    st = twin_state(
        mass,
        params,
        effects,
        tcp_rows.a_deg,
        tcp_rows.dir,
        tcp_rows.payload_kg,
        tcp_rows.temp_c,
        clock=tcp_rows.clock,
    )
    flange = st.chain.world_T_frame[:, 6]
    expected = np.concatenate(
        [st.tcp_mm, *(flange[:, :3, :3] @ place + flange[:, :3, 3] for place in FURTHER_TARGETS_MM)]
    )
    np.testing.assert_allclose(predict_mm(mass, params, effects, obs), expected, rtol=0.0, atol=1e-9)
    resid, _, _ = linearize_targets(mass, params, effects, [], obs)
    np.testing.assert_allclose(-resid, expected, rtol=0.0, atol=1e-9)


def test_the_shared_jacobian_of_every_target_is_exact() -> None:
    """Every column (geometric, effects, the further targets' places) against central differences of
    the predictions, a drift included (the base rotation turns the TCP, not the drift's
    translation); the compliance at zero (the twin's Jacobian leaves out the torque's dependence on
    the geometry)."""
    mass, params, effects, obs = _three_targets(payload_kg=2.0)
    effects = effects.with_values(["C2", "C3"], [0.0, 0.0])
    names = ["h2", "eps3", "c4_1", "s5_2", "C2", "C3", "kappa", "vx", "wz"]
    resid, jac, tcols = linearize_targets(mass, params, effects, names, obs)
    assert np.all(jac[len(obs) // 3 :, :, TOOL_SLICE] == 0.0)  # the further targets' tool is their place

    def pred(p: KinematicParams, e: EffectParams, o: MeasuredRows = obs) -> np.ndarray:
        return predict_mm(mass, p, e, o)

    for col in range(N_PARAMS):
        h = 1e-6 if col % 5 in (0, 3, 4) or col >= 33 else 1e-4
        dx = np.zeros(N_PARAMS)
        dx[col] = h
        numeric = (pred(params.apply(dx), effects) - pred(params.apply(-dx), effects)) / (2 * h)
        if TOOL_SLICE.start <= col < TOOL_SLICE.stop:
            numeric[len(obs) // 3 :] = 0.0
        np.testing.assert_allclose(
            jac[:, :, col], numeric, rtol=0.0, atol=1e-6 * max(1.0, np.abs(numeric).max())
        )
    for k, name in enumerate(names):
        h = 1e-4 * max(abs(float(effects.get([name])[0])), 1e-2)
        numeric = (pred(params, effects.add([name], [h])) - pred(params, effects.add([name], [-h]))) / (2 * h)
        col = jac[:, :, N_PARAMS + k]
        np.testing.assert_allclose(col, numeric, rtol=0.0, atol=1e-6 * max(1.0, np.abs(numeric).max()))
    assert obs.target_offsets_mm is not None
    for k in range(3 * len(FURTHER_TARGETS_MM)):
        step = np.zeros_like(obs.target_offsets_mm)
        step.flat[k] = 1e-3
        up = dataclasses.replace(obs, target_offsets_mm=obs.target_offsets_mm + step)
        down = dataclasses.replace(obs, target_offsets_mm=obs.target_offsets_mm - step)
        numeric = (pred(params, effects, up) - pred(params, effects, down)) / 2e-3
        np.testing.assert_allclose(tcols[:, :, k], numeric, rtol=0.0, atol=1e-8)
    assert resid.shape == (len(obs), 3)


def test_the_batched_fold_solves_are_the_folds_least_squares() -> None:
    """Cross-validated error and out-of-fold residuals of a model: every fold's least squares on the
    other folds' rows, predicted on its own."""
    rng = np.random.default_rng(5)
    n, m = 120, 9
    jac = rng.normal(size=(n, 3, m)) * np.logspace(-3, 3, m)  # columns of very different scales
    resid = jac[:, :, :4] @ rng.normal(size=4) + rng.normal(0.0, 0.1, (n, 3))
    fold = make_folds(np.arange(n) // 3, 5, 1)
    lp = LinearProblem(resid, jac, np.arange(n) // 3, fold)
    for cols in ([0, 1, 2, 3], [1, 4, 7, 8], [5]):
        sse, oof = 0.0, np.empty_like(resid)
        for f in range(5):
            train, test = fold != f, fold == f
            step, *_ = np.linalg.lstsq(jac[train][:, :, cols].reshape(-1, len(cols)), resid[train].ravel())
            oof[test] = resid[test] - jac[test][:, :, cols] @ step
            sse += float(np.sum(oof[test] ** 2))
        assert lp.cv_sse(cols) == pytest.approx(sse, rel=1e-9)
        np.testing.assert_allclose(lp.oof_residuals(cols), oof, rtol=0.0, atol=1e-9)
    assert lp.cv_sse([]) == pytest.approx(float(np.sum(resid**2)), rel=1e-12)
