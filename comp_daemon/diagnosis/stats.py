"""Cross-validation and significance tests on the linearised twin.

A :class:`LinearProblem` holds, for the fit rows, the residual ``r`` (mm, 3 per pose) of a twin
and its Jacobian ``J`` with respect to every parameter that any candidate model may free, columns
scaled to unit norm. A model is a set of column indices; fitting it is the linear least squares
``min ‖r − J_S·δ‖`` (exact for the effects, which enter the twin linearly to well below the
tracker's noise, and exact for the geometry at the Gauss–Newton optimum of the base model).

* Cross-validation: k folds of *pose groups* (repeats of a pose stay together), chosen once by a
  seeded generator; a model's CV error is the RMS 3-D distance on the held-out poses. Every fold
  is solved from Gram matrices (``JᵀJ`` minus the fold's share), so one candidate costs a few
  small solves whatever the number of poses.
* Significance: a Wald test of the added columns with a cluster-robust covariance (clusters =
  pose groups, leverage-corrected "CR3" residuals ``(I − H_gg)⁻¹ e_g``, which approximate the
  jackknife). It does not assume that x, y, z of a pose are independent or equally noisy: the
  tracker's noise is, the robot's joint repeatability moves the TCP along the very directions
  that the joint effects produce, and an ordinary F-test would count that as signal. The
  statistic ``W/q`` is referred to an F(q, G − 1) distribution (G clusters).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.stats
from numpy.typing import NDArray

__all__ = ["LinearProblem", "WaldResult", "make_folds"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def make_folds(pose_group: IntArray, k: int, seed: int) -> IntArray:
    """(n,) fold number 0..k−1 of each row; every pose group lies in one fold.

    Groups are shuffled by ``numpy.random.default_rng(seed)`` and dealt round-robin, so folds
    differ in size by at most one group.
    """
    groups, inverse = np.unique(pose_group, return_inverse=True)
    k = max(1, min(int(k), len(groups)))
    order = np.random.default_rng(seed).permutation(len(groups))
    fold_of_group = np.empty(len(groups), dtype=np.int64)
    fold_of_group[order] = np.arange(len(groups)) % k
    return fold_of_group[np.asarray(inverse).reshape(-1)]


@dataclass(frozen=True)
class WaldResult:
    statistic: float  # W / q
    dof: int  # q, the number of tested columns
    clusters: int
    p_value: float


class LinearProblem:
    """The linearised least-squares problem on the fit rows (see the module docstring).

    ``resid_mm`` (n, 3), ``jac`` (n, 3, m) raw columns, ``pose_group`` (n,), ``fold`` (n,).
    """

    def __init__(self, resid_mm: FloatArray, jac: FloatArray, pose_group: IntArray, fold: IntArray) -> None:
        n, _, m = jac.shape
        self.n = n
        self.m = m
        norms = np.linalg.norm(jac.reshape(-1, m), axis=0)
        self.col_norm = np.where(norms > 0.0, norms, 1.0)
        self.jac = jac / self.col_norm  # (n, 3, m) unit-norm columns
        self.r = resid_mm  # (n, 3)
        self.fold = fold
        self.k = int(fold.max()) + 1 if n else 0
        _, self.cluster = np.unique(pose_group, return_inverse=True)
        self.cluster = np.asarray(self.cluster).reshape(-1)
        self.n_clusters = int(self.cluster.max()) + 1 if n else 0
        jf = self.jac.reshape(-1, m)
        rf = self.r.reshape(-1)
        self.gram = jf.T @ jf
        self.jtr = jf.T @ rf
        self.rtr = float(rf @ rf)
        self.fold_gram = np.empty((self.k, m, m))
        self.fold_jtr = np.empty((self.k, m))
        self.fold_rtr = np.empty(self.k)
        for f in range(self.k):
            rows = self.fold == f
            jr = self.jac[rows].reshape(-1, m)
            rr = self.r[rows].reshape(-1)
            self.fold_gram[f] = jr.T @ jr
            self.fold_jtr[f] = jr.T @ rr
            self.fold_rtr[f] = float(rr @ rr)
        self.fold_rows = np.bincount(self.fold, minlength=self.k)

    # ---- fitting ---------------------------------------------------------------------------
    @staticmethod
    def _solve(gram: FloatArray, rhs: FloatArray) -> FloatArray:
        try:
            return np.asarray(scipy.linalg.solve(gram, rhs, assume_a="pos", check_finite=False))
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            return np.asarray(np.linalg.lstsq(gram, rhs, rcond=None)[0])

    def solve(self, cols: Sequence[int]) -> FloatArray:
        """Scaled least-squares step of the model ``cols`` on all fit rows."""
        idx = np.asarray(cols, dtype=np.int64)
        if len(idx) == 0:
            return np.zeros(0)
        return self._solve(self.gram[np.ix_(idx, idx)], self.jtr[idx])

    def unscale(self, cols: Sequence[int], step: FloatArray) -> FloatArray:
        """A scaled step back in the parameters' own units."""
        return step / self.col_norm[np.asarray(cols, dtype=np.int64)]

    def sse(self, cols: Sequence[int]) -> float:
        """In-sample sum of squared residuals (mm²) of the model ``cols``."""
        idx = np.asarray(cols, dtype=np.int64)
        if len(idx) == 0:
            return self.rtr
        step = self.solve(cols)
        return float(self.rtr - step @ self.jtr[idx])

    def _fold_steps(self, idx: IntArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per fold, the model ``idx`` fitted without the fold: the scaled steps (k, p), and the
        fold's own Gram matrices (k, p, p) and ``Jᵀr`` (k, p). The k solves are one batched call."""
        fold_gram = self.fold_gram[:, idx][:, :, idx]
        fold_jtr = self.fold_jtr[:, idx]
        g_train = self.gram[np.ix_(idx, idx)] - fold_gram
        b_train = self.jtr[idx] - fold_jtr
        try:
            steps = scipy.linalg.solve(g_train, b_train[:, :, None], assume_a="pos", check_finite=False)[
                :, :, 0
            ]
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            steps = np.array([self._solve(g, b) for g, b in zip(g_train, b_train, strict=True)])
        return np.asarray(steps), fold_gram, fold_jtr

    def cv_sse(self, cols: Sequence[int]) -> float:
        """Sum over folds of the held-out squared residuals (mm²) of the model ``cols``."""
        idx = np.asarray(cols, dtype=np.int64)
        if len(idx) == 0:
            return float(sum(float(v) for v in self.fold_rtr))
        steps, fold_gram, fold_jtr = self._fold_steps(idx)
        total = 0.0
        for f in range(self.k):
            step = steps[f]
            total += self.fold_rtr[f] - 2.0 * step @ fold_jtr[f] + step @ fold_gram[f] @ step
        return float(total)

    def oof_residuals(self, cols: Sequence[int]) -> FloatArray:
        """(n, 3) residuals of every fit row under the model ``cols`` fitted without its fold (mm)."""
        idx = np.asarray(cols, dtype=np.int64)
        out = self.r.copy()
        if len(idx) == 0:
            return out
        steps, _, _ = self._fold_steps(idx)
        for f in range(self.k):
            rows = self.fold == f
            out[rows] = self.r[rows] - self.jac[rows][:, :, idx] @ steps[f]
        return out

    def cv_rms_mm(self, cols: Sequence[int]) -> float:
        """RMS 3-D distance over held-out poses of the model ``cols`` (mm)."""
        return float(np.sqrt(max(self.cv_sse(cols), 0.0) / max(self.n, 1)))

    # ---- significance ----------------------------------------------------------------------
    def _robust_fit(self, idx: IntArray) -> tuple[FloatArray, FloatArray]:
        """Scaled step and its cluster-robust covariance of the model ``idx``."""
        gram = self.gram[np.ix_(idx, idx)]
        bread = np.linalg.pinv(gram, hermitian=True)
        step = bread @ self.jtr[idx]
        js = self.jac[:, :, idx]  # (n, 3, p)
        e = self.r - js @ step  # (n, 3)
        # leverage correction per pose (one pose per cluster is the common case; larger clusters
        # are corrected pose by pose, which is CR3 up to the cross-pose leverage terms)
        h = js @ bread @ js.transpose(0, 2, 1)  # (n, 3, 3)
        eye = np.eye(3)
        e_adj = np.linalg.solve(eye - h + 1e-12 * eye, e[:, :, None])[:, :, 0]
        score = np.einsum("nkp,nk->np", js, e_adj)  # (n, p)
        per_cluster = np.zeros((self.n_clusters, len(idx)))
        np.add.at(per_cluster, self.cluster, score)
        meat = per_cluster.T @ per_cluster
        return step, bread @ meat @ bread

    def standard_errors(self, cols: Sequence[int]) -> FloatArray:
        """Cluster-robust (pose-clustered) standard errors of the model ``cols``'s parameters, in
        their own units (the covariance of :meth:`wald`)."""
        idx = np.asarray(cols, dtype=np.int64)
        _, cov = self._robust_fit(idx)
        return np.sqrt(np.clip(np.diag(cov), 0.0, None)) / self.col_norm[idx]

    def wald(self, cols: Sequence[int], tested: Sequence[int], at: FloatArray | None = None) -> WaldResult:
        """Cluster-robust Wald test that the ``tested`` parameters (a subset of ``cols``) are zero.

        ``at`` (m,) holds the parameters' values at the linearisation point in their own units (the
        problem's residual is measured from there); omitted, they are zero.
        """
        idx = np.asarray(cols, dtype=np.int64)
        pos = np.array([int(np.flatnonzero(idx == t)[0]) for t in tested], dtype=np.int64)
        q = len(pos)
        g = self.n_clusters
        step, cov = self._robust_fit(idx)
        sub = cov[np.ix_(pos, pos)]
        beta = step[pos]
        if at is not None:
            beta = beta + (np.asarray(at, dtype=float) * self.col_norm)[idx[pos]]
        try:
            w = float(beta @ np.linalg.solve(sub, beta))
        except np.linalg.LinAlgError:
            w = float(beta @ np.linalg.pinv(sub) @ beta)
        stat = w / max(q, 1)
        dof2 = max(g - 1, 1)
        p_value = float(scipy.stats.f.sf(stat, q, dof2)) if q else 1.0
        return WaldResult(statistic=stat, dof=q, clusters=g, p_value=p_value)
