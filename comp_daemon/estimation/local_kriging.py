"""Ordinary kriging in local neighbourhoods: each query solved on its k nearest sampling points.

The dense predictor of :class:`comp_daemon.models.kriging.OrdinaryKriging` factorises one n × n
system: with 10 000 sampling points that is 800 MB per matrix and a cubic solve. Kriging weights
fall off with the correlation, so the prediction at a state ``s0`` is carried by its neighbours;
the local predictor solves, for every query, the ordinary-kriging system of seed 001 eq. 26 on the
``k`` samples nearest to it in the model's own metric (the Euclidean distance of the joint-state
coordinates, found with a k-d tree, :class:`scipy.spatial.cKDTree`)::

    [R_k  1] [λ]   [r_k]
    [1ᵀ   0] [ν] = [1  ]        ẑ0 = λᵀ z_k,   MSE = σ²·(1 − λᵀr_k − ν)

(``R_k`` the correlation of the k neighbours with the nugget ratio on its diagonal, ``r_k`` their
correlation with ``s0``, ``σ²`` the partial sill). With ``k = n`` this is the dense predictor and
its variance, to rounding. Queries are solved in batches (one stacked LU solve per batch and
error component); nothing is factorised at fit time, so fitting is the tree build.

Leave-one-out residuals are the same predictor at each sample with the sample itself left out of
its neighbourhood.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from comp_daemon.estimation.ordinary_kriging import kriging_queries, kriging_samples
from comp_daemon.estimation.variogram import VariogramModel

__all__ = ["LocalKriging"]

BATCH = 512  # queries per stacked solve at most
BATCH_ELEMENTS = 4_000_000  # and at most this many elements in one component's (batch, k+1, k+1) array


class LocalKriging:
    """Ordinary kriging of k components on ``neighbours`` nearest samples per query.

    ``coords`` (n, d), ``values`` (n, k), ``variograms`` one per component, as
    :class:`~comp_daemon.models.kriging.OrdinaryKriging`.
    """

    def __init__(
        self,
        coords: NDArray[np.float64],
        values: NDArray[np.float64],
        variograms: Sequence[VariogramModel],
        neighbours: int,
    ) -> None:
        x, z = kriging_samples(coords, values, variograms)
        if int(neighbours) < 2:
            raise ValueError(f"a kriging neighbourhood needs at least 2 samples, got {neighbours}")
        self.coords = x
        self.values = z
        self.variograms = tuple(variograms)
        self.neighbours = min(int(neighbours), x.shape[0])
        self.tree = cKDTree(x)
        self.batch = max(1, min(BATCH, BATCH_ELEMENTS // (self.neighbours + 2) ** 2))
        self._a: NDArray[np.float64] | None = None
        self._rhs: NDArray[np.float64] | None = None

    @property
    def n_samples(self) -> int:
        return int(self.coords.shape[0])

    def _work(self, n_comp: int, m: int, kn: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The bordered systems (n_comp, m, kn+1, kn+1) and right-hand sides, reused between
        batches (allocating them anew each batch costs as much as filling them)."""
        shape = (n_comp, self.batch, kn + 1, kn + 1)
        if self._a is None or self._a.shape != shape:
            self._a = np.empty(shape)
            self._rhs = np.empty((n_comp, self.batch, kn + 1, 1))
        assert self._rhs is not None
        a, rhs = self._a[:, :m], self._rhs[:, :m]
        a[:, :, :kn, kn] = 1.0
        a[:, :, kn, :kn] = 1.0
        a[:, :, kn, kn] = 0.0
        rhs[:, :, kn, 0] = 1.0
        return a, rhs

    def _solve(
        self, q: NDArray[np.float64], idx: NDArray[np.intp], return_std: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Predictions (m, k) (and kriging std) at ``q`` (m, d) from the samples ``idx`` (m, kn).

        The systems of every component are stacked and solved in one batched call."""
        m, kn = idx.shape
        pts = self.coords[idx]  # (m, kn, d)
        centred = pts - pts.mean(axis=1, keepdims=True)  # Gram form, centred to keep the digits
        sq = np.einsum("mid,mid->mi", centred, centred)
        d2 = np.matmul(centred, np.ascontiguousarray(centred.transpose(0, 2, 1)))
        d2 *= -2.0
        d2 += sq[:, :, None]
        d2 += sq[:, None, :]
        np.maximum(d2, 0.0, out=d2)  # squared sample-sample distances
        diff = pts - q[:, None, :]
        d2_q = np.einsum("mkd,mkd->mk", diff, diff)  # squared query-sample distances
        n_comp = self.values.shape[1]
        a, rhs = self._work(n_comp, m, kn)
        diag = np.arange(kn)
        for c, vg in enumerate(self.variograms):
            vg.correlation_of_squared(d2, out=a[c, :, :kn, :kn])
            a[c, :, diag, diag] = 1.0 + vg.nugget / vg.psill
            vg.correlation_of_squared(d2_q, out=rhs[c, :, :kn, 0])
        sol = np.linalg.solve(a.reshape(-1, kn + 1, kn + 1), rhs.reshape(-1, kn + 1, 1))
        sol = sol.reshape(n_comp, m, kn + 1)
        lam = sol[:, :, :kn]  # (k, m, kn)
        out = np.einsum("cmk,mkc->mc", lam, self.values[idx])
        std = None
        if return_std:
            mse = 1.0 - np.einsum("cmk,cmk->cm", lam, rhs[:, :, :kn, 0]) - sol[:, :, kn]  # (k, m)
            psill = np.array([vg.psill for vg in self.variograms])
            std = np.sqrt(np.maximum(psill[:, None] * mse, 0.0)).T
        return out, std

    def predict(
        self, coords: NDArray[np.float64], *, return_std: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(m, k) predictions at ``coords`` (m, d); with ``return_std`` also the kriging std (m, k)."""
        q = kriging_queries(coords, self.coords)
        out = np.empty((q.shape[0], self.values.shape[1]))
        std = np.empty_like(out) if return_std else None
        for start in range(0, q.shape[0], self.batch):
            block = q[start : start + self.batch]
            _, idx = self.tree.query(block, k=self.neighbours)
            idx = np.asarray(idx, dtype=np.intp).reshape(block.shape[0], self.neighbours)
            pred, s = self._solve(block, idx, return_std)
            out[start : start + len(block)] = pred
            if std is not None and s is not None:
                std[start : start + len(block)] = s
        if std is not None:
            return out, std
        return out

    def loo_residuals(self, rows: NDArray[np.intp] | None = None) -> NDArray[np.float64]:
        """Leave-one-out residuals ``z_i − ẑ_{−i}`` (len(rows), k) at the samples ``rows`` (default all)."""
        sel = np.arange(self.n_samples) if rows is None else np.asarray(rows, dtype=np.intp)
        kn = min(self.neighbours, self.n_samples - 1)
        out = np.empty((sel.size, self.values.shape[1]))
        for start in range(0, sel.size, self.batch):
            rows_b = sel[start : start + self.batch]
            _, idx = self.tree.query(self.coords[rows_b], k=kn + 1)
            idx = np.asarray(idx, dtype=np.intp).reshape(rows_b.size, kn + 1)
            # drop the sample itself (first unless a duplicate state came first)
            keep = idx != rows_b[:, None]
            drop_last = keep.all(axis=1)
            keep[drop_last, -1] = False
            idx = idx[keep].reshape(rows_b.size, kn)
            pred, _ = self._solve(self.coords[rows_b], idx, False)
            out[start : start + rows_b.size] = self.values[rows_b] - pred
        return out
