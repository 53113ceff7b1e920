"""The diagnosis's fast paths against their plain references.

* The remainder's structure test computes the out-of-fold shares of every permutation at once; a
  direct loop (bin means on each fold's training rows, predicted on its held-out rows) gives the
  same shares and the same decisions.
"""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.diagnosis import structure
from comp_daemon.diagnosis.stats import make_folds


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
