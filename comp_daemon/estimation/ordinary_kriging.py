"""Dense ordinary kriging (seed 001 eqs 18–28): one factorised system over every sampling point.

The equations are those of :mod:`comp_daemon.models.kriging`'s docstring; this module solves them
for k value components on shared coordinates with the Cholesky factor of the n × n correlation
matrix (nugget ratio on its diagonal), and gives the leave-one-out residuals in closed form.
:mod:`comp_daemon.estimation.local_kriging` solves the same system on the k nearest samples of each
query instead, for sampling sets too large for one dense system.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from comp_daemon.estimation.variogram import VariogramModel, pairwise_distances

__all__ = ["OrdinaryKriging", "kriging_queries", "kriging_samples"]

AXES = ("x", "y", "z")


def kriging_samples(
    coords: NDArray[np.float64], values: NDArray[np.float64], variograms: Sequence[VariogramModel]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sample coordinates (n, d) and values (n, k) checked for kriging (ValueError naming the fault)."""
    x = np.asarray(coords, dtype=float)
    z = np.asarray(values, dtype=float)
    if z.ndim == 1:
        z = z[:, None]
    if x.ndim != 2 or z.ndim != 2 or x.shape[0] != z.shape[0]:
        raise ValueError(f"coords (n, d) and values (n, k) must have the same n, got {x.shape}, {z.shape}")
    if x.shape[0] < 2:
        raise ValueError(f"kriging needs at least 2 samples, got {x.shape[0]}")
    if len(variograms) != z.shape[1]:
        raise ValueError(f"{z.shape[1]} components but {len(variograms)} variograms")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(z))):
        raise ValueError("kriging samples must be finite")
    return x, z


def kriging_queries(coords: NDArray[np.float64], samples: NDArray[np.float64]) -> NDArray[np.float64]:
    """Query coordinates (m, d) checked against the samples' (n, d) (ValueError naming the shapes)."""
    q = np.asarray(coords, dtype=float)
    if q.ndim != 2 or q.shape[1] != samples.shape[1]:
        raise ValueError(f"query coordinates must be (m, {samples.shape[1]}), got {q.shape}")
    return q


class OrdinaryKriging:
    """Ordinary kriging of k components on shared coordinates, one fitted variogram per component.

    ``coords`` (n, d), ``values`` (n, k), ``variograms`` k models. Solved as in the module docstring;
    ``alpha``/``beta`` may be given (a stored model) to skip the solve for prediction; ``distances``
    (n, n) among the samples, if already computed.
    """

    def __init__(
        self,
        coords: NDArray[np.float64],
        values: NDArray[np.float64],
        variograms: Sequence[VariogramModel],
        *,
        alpha: NDArray[np.float64] | None = None,
        beta: NDArray[np.float64] | None = None,
        distances: NDArray[np.float64] | None = None,
    ) -> None:
        x, z = kriging_samples(coords, values, variograms)
        self.coords = x
        self.values = z
        self.variograms = tuple(variograms)
        self._dist: NDArray[np.float64] | None = None if distances is None else np.asarray(distances)
        self._factors: list[tuple[NDArray[np.float64], bool]] | None = None
        self._ones: list[NDArray[np.float64]] | None = None  # R⁻¹1 per component
        if alpha is not None and beta is not None:
            self.alpha = np.asarray(alpha, dtype=float)
            self.beta = np.asarray(beta, dtype=float)
            if self.alpha.shape != z.shape or self.beta.shape != (z.shape[1],):
                raise ValueError(f"alpha must be {z.shape} and beta ({z.shape[1]},)")
        else:
            self._solve()

    @property
    def n_samples(self) -> int:
        return int(self.coords.shape[0])

    def _sample_distances(self) -> NDArray[np.float64]:
        if self._dist is None:
            self._dist = pairwise_distances(self.coords)
        return self._dist

    def _factorise(self) -> None:
        if self._factors is not None:
            return
        dist = self._sample_distances()
        n = dist.shape[0]
        factors: list[tuple[NDArray[np.float64], bool]] = []
        ones: list[NDArray[np.float64]] = []
        # a pair of samples at distance ~0 (the n zeros of the diagonal aside)
        has_duplicates = int(np.count_nonzero(dist <= 1e-9 * max(float(dist.max()), 1e-300))) > n
        for c, vg in enumerate(self.variograms):
            if has_duplicates and vg.nugget == 0.0:
                raise ValueError(
                    _singular_message(dist, vg, AXES[c] if len(self.variograms) == 3 else str(c))
                )
            r = vg.correlation(dist)
            r[np.diag_indices(n)] = 1.0 + vg.nugget / vg.psill
            factor = None
            for jitter in (0.0, 1e-10, 1e-8):
                try:
                    factor = scipy.linalg.cho_factor(
                        r + jitter * np.eye(n) if jitter else r, lower=True, check_finite=False
                    )
                    break
                except np.linalg.LinAlgError:
                    continue
            if factor is None:
                raise ValueError(
                    _singular_message(dist, vg, AXES[c] if len(self.variograms) == 3 else str(c))
                )
            factors.append(factor)
            ones.append(scipy.linalg.cho_solve(factor, np.ones(n), check_finite=False))
        self._factors = factors
        self._ones = ones

    def _solve(self) -> None:
        self._factorise()
        assert self._factors is not None and self._ones is not None
        k = self.values.shape[1]
        alpha = np.empty_like(self.values)
        beta = np.empty(k)
        for c in range(k):
            z = self.values[:, c]
            v = self._ones[c]
            rz = scipy.linalg.cho_solve(self._factors[c], z, check_finite=False)
            beta[c] = float(v @ z) / float(v.sum())
            alpha[:, c] = rz - beta[c] * v  # R⁻¹(z − 1β)
        self.alpha = alpha
        self.beta = beta

    def predict(
        self, coords: NDArray[np.float64], *, return_std: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(m, k) predictions at ``coords`` (m, d); with ``return_std`` also the kriging std (m, k)."""
        q = kriging_queries(coords, self.coords)
        dist = pairwise_distances(q, self.coords)
        k = self.values.shape[1]
        out = np.empty((q.shape[0], k))
        std = np.empty((q.shape[0], k)) if return_std else None
        for c, vg in enumerate(self.variograms):
            r = vg.correlation(dist)  # (m, n)
            out[:, c] = self.beta[c] + r @ self.alpha[:, c]
            if std is not None:
                self._factorise()
                assert self._factors is not None and self._ones is not None
                rr = scipy.linalg.cho_solve(self._factors[c], r.T, check_finite=False)  # (n, m)
                v = self._ones[c]
                lag_term = 1.0 - v @ r.T  # 1 − 1ᵀR⁻¹r
                mse = 1.0 - np.einsum("mn,nm->m", r, rr) + lag_term**2 / float(v.sum())
                std[:, c] = np.sqrt(np.maximum(vg.psill * mse, 0.0))
        if std is not None:
            return out, std
        return out

    def weights(self, coords: NDArray[np.float64], component: int = 0) -> NDArray[np.float64]:
        """(m, n) kriging weights λ of the samples for each query (each row sums to 1)."""
        self._factorise()
        assert self._factors is not None and self._ones is not None
        q = np.asarray(coords, dtype=float)
        r = self.variograms[component].correlation(pairwise_distances(q, self.coords))
        rr = scipy.linalg.cho_solve(self._factors[component], r.T, check_finite=False)  # (n, m)
        v = self._ones[component]
        return (rr + np.outer(v, 1.0 - v @ r.T) / float(v.sum())).T

    def loo_residuals(self) -> NDArray[np.float64]:
        """(n, k) leave-one-out residuals ``z_i − ẑ_{−i}`` in closed form (Dubrule's formula).

        With ``Q`` the sample block of the inverse of the bordered kriging matrix,
        ``Q = R⁻¹ − R⁻¹11ᵀR⁻¹/1ᵀR⁻¹1``, the residual is ``α_i / Q_ii``.
        """
        self._factorise()
        assert self._factors is not None and self._ones is not None
        out = np.empty_like(self.values)
        for c in range(self.values.shape[1]):
            # R = L Lᵀ, so (R⁻¹)_ii = Σ_k (L⁻¹)_ki²: one triangular inverse, not n solves
            fac, lower = self._factors[c]
            inv, info = scipy.linalg.lapack.dtrtri(fac if lower else fac.T, lower=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"kriging matrix of component {c}: singular factor ({info})")
            inv = np.tril(inv)  # the upper triangle holds what the factorisation left there
            rinv_diag = np.einsum("ki,ki->i", inv, inv)
            v = self._ones[c]
            q_diag = rinv_diag - v * v / float(v.sum())
            out[:, c] = self.alpha[:, c] / q_diag
        return out


def _singular_message(dist: NDArray[np.float64], vg: VariogramModel, comp: str) -> str:
    n = dist.shape[0]
    iu, ju = np.triu_indices(n, k=1)
    dup = np.flatnonzero(dist[iu, ju] <= 1e-9 * max(float(dist.max()), 1e-300))
    if dup.size and vg.nugget == 0.0:
        i, j = int(iu[dup[0]]), int(ju[dup[0]])
        return (
            f"kriging system of component {comp} is singular: samples {i + 1} and {j + 1} are the same "
            f"joint state ({dup.size} such pair(s)); fit a variogram with a nugget or drop repeats"
        )
    return f"kriging system of component {comp} is not positive definite ({vg.kind} model)"
