"""A non-parametric remainder model: what is left in joint space after the best parametric twin.

Structure that no effect of the vocabulary names (a transmission error of a higher harmonic than
the catalogue tries, a deformation the compliance model does not describe) leaves the remainder of
the final parametric model a smooth function of the axis values. This module puts a Gaussian
process on it, with one length scale per moving joint (anisotropic), and keeps it only when it
wins out of fold.

Model. The remainder ``e`` (mm, one column per measured coordinate) of a row with axis values
``A`` (deg) is ``f(A) + noise``; each column has its own smooth ``f`` but all share one covariance

    k(A, A') = s · exp(−½ Σ_j (A_j − A'_j)² / ℓ_j²)   plus   σ² on the diagonal

(``s`` the signal variance, ``ℓ_j`` the length scale of joint j in deg, ``σ²`` the variance of
what is not smooth: tracker noise, repeatability). The hyperparameters maximise the marginal
likelihood of the remainder (summed over the columns; L-BFGS-B with analytic gradients, on at
most :data:`HYPER_MAX_ROWS` rows). Prediction is ordinary kriging
(:class:`~comp_daemon.estimation.ordinary_kriging.OrdinaryKriging`, seed 001 eqs 18–28) on the joint
values divided by the length scales, with a Gaussian variogram of range √6 (so that its
correlation ``exp(−3h²/6)`` is the kernel above), partial sill ``s`` and nugget ``σ²``: the
Gaussian-process mean with an unknown constant mean per column. Beyond
:data:`DENSE_MAX_ROWS` training rows each query is kriged on its :data:`NEIGHBOURS` nearest rows
(:class:`~comp_daemon.estimation.local_kriging.LocalKriging`).

Judged out of fold. On the fit rows, for each of the diagnosis' k folds (of pose groups): the
parametric model (the final model's linear problem) is fitted without the fold, the Gaussian
process (hyperparameters included) is fitted on the remainder of the other folds, and predicts the
fold's remainder. The model is **kept** when the cross-validated RMS falls by at least
:data:`MIN_GAIN_PCT` % and the per-pose-group gain in squared error is positive at
:data:`ALPHA` (one-sided t-test over the pose groups). A pure-noise remainder is predicted by a
near-zero function and fails both. The model reported is then fitted on every fit row (length
scales, signal and noise: the geometric mean of the folds' values) and judged on check rows as
every step of the ladder is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.optimize
import scipy.stats
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.diagnosis.stats import LinearProblem
from comp_daemon.estimation.local_kriging import LocalKriging
from comp_daemon.estimation.ordinary_kriging import OrdinaryKriging
from comp_daemon.estimation.variogram import VariogramModel

__all__ = [
    "ALPHA",
    "DENSE_MAX_ROWS",
    "HYPER_MAX_ROWS",
    "MIN_GAIN_PCT",
    "GPHyper",
    "GaussianProcessRemainder",
    "RemainderModel",
    "fit_hyperparameters",
    "judge_remainder",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

log = get_logger(__name__)

#: the cross-validated RMS must fall by at least this much (%) for the model to be kept
MIN_GAIN_PCT = 2.0
#: one-sided level of the per-pose-group test of the out-of-fold gain
ALPHA = 0.01
#: the hyperparameters are fitted on at most this many rows (drawn reproducibly)
HYPER_MAX_ROWS = 200
#: at most this many L-BFGS-B iterations for the hyperparameters
HYPER_MAX_ITER = 60
#: above this many training rows the prediction is kriged in local neighbourhoods
DENSE_MAX_ROWS = 2000
#: rows per local neighbourhood
NEIGHBOURS = 64
#: fewest fit rows (and pose groups) the model is tried on
MIN_ROWS = 30
#: a joint that moves less than this (deg) over the fit rows gets no length scale
MIN_SPAN_DEG = 1e-6
#: range of the Gaussian variogram whose correlation exp(−3h²/a²) is exp(−h²/2)
_GAUSSIAN_RANGE = math.sqrt(6.0)


@dataclass(frozen=True)
class GPHyper:
    """Hyperparameters: length scales (deg) of the joints used, signal and noise variance (mm²)."""

    joints: tuple[int, ...]  # 0-based columns of the axis values the kernel reads
    length_deg: FloatArray
    signal_var: float
    noise_var: float

    def coords(self, a_deg: FloatArray) -> FloatArray:
        return np.asarray(a_deg, dtype=float)[:, list(self.joints)] / self.length_deg

    def variogram(self) -> VariogramModel:
        return VariogramModel("gaussian", self.noise_var, self.signal_var, _GAUSSIAN_RANGE)


def _subset(n: int, most: int, seed: int) -> NDArray[np.intp]:
    if n <= most:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, most, replace=False))


def _inverse_from_cholesky(lower: FloatArray) -> FloatArray:
    """K⁻¹ from the lower Cholesky factor of K (LAPACK potri, then the upper triangle mirrored)."""
    inv, info = scipy.linalg.lapack.dpotri(lower, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"potri failed ({info})")
    low = np.tril(inv)
    out: FloatArray = low + np.tril(inv, -1).T
    return out


def fit_hyperparameters(
    a_deg: FloatArray, resid_mm: FloatArray, joints: Sequence[int], *, seed: int = 0
) -> GPHyper:
    """Maximum marginal likelihood hyperparameters of the remainder ``resid_mm`` (n, k) on ``a_deg``.

    One covariance for all k columns (each centred on its mean); at most :data:`HYPER_MAX_ROWS`
    rows are used. Length scales are bounded to [0.05, 50] × the joint's spread, the noise variance
    below by 1e-6 of the remainder's variance.
    """
    idx = _subset(len(a_deg), HYPER_MAX_ROWS, seed)
    x = np.asarray(a_deg, dtype=float)[idx][:, list(joints)]
    y = np.asarray(resid_mm, dtype=float)[idx]
    y = y - y.mean(axis=0)
    n, k = y.shape
    scale = float(np.sqrt(np.mean(y**2))) or 1.0
    y = y / scale
    spread = np.maximum(np.std(x, axis=0), 1e-9)
    sq = np.stack([(x[:, j, None] - x[None, :, j]) ** 2 for j in range(x.shape[1])])  # (d, n, n)
    d = x.shape[1]
    eye = np.eye(n)

    def nll(theta: FloatArray) -> tuple[float, FloatArray]:
        ell2 = np.exp(2.0 * theta[:d])
        s, noise = math.exp(theta[d]), math.exp(theta[d + 1])
        kf = s * np.exp(-0.5 * np.tensordot(1.0 / ell2, sq, axes=1))
        kmat = kf + noise * eye
        try:
            c = scipy.linalg.cho_factor(kmat, lower=True, check_finite=False)
            kinv = _inverse_from_cholesky(c[0])
        except np.linalg.LinAlgError:
            return 1e30, np.zeros_like(theta)
        alpha = scipy.linalg.cho_solve(c, y, check_finite=False)
        logdet = 2.0 * float(np.sum(np.log(np.diag(c[0]))))
        value = 0.5 * float(np.sum(y * alpha)) + 0.5 * k * logdet
        w = alpha @ alpha.T - k * kinv
        grad = np.empty_like(theta)
        wk = w * kf
        grad[:d] = -0.5 * np.tensordot(sq, wk, axes=([1, 2], [0, 1])) / ell2
        grad[d] = -0.5 * float(np.sum(wk))
        grad[d + 1] = -0.5 * noise * float(np.trace(w))
        return value, grad

    start = np.concatenate([np.log(spread), [math.log(0.5), math.log(0.5)]])
    bounds = [(math.log(0.05 * s), math.log(50.0 * s)) for s in spread]
    bounds += [(math.log(1e-6), math.log(10.0)), (math.log(1e-6), math.log(10.0))]
    res = scipy.optimize.minimize(
        nll,
        start,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": HYPER_MAX_ITER, "ftol": 1e-7, "gtol": 1e-4},
    )
    theta = res.x
    return GPHyper(
        joints=tuple(int(j) for j in joints),
        length_deg=np.exp(theta[:d]),
        signal_var=math.exp(theta[d]) * scale**2,
        noise_var=math.exp(theta[d + 1]) * scale**2,
    )


class GaussianProcessRemainder:
    """The kriging predictor of a remainder (n, k) at the axis values of its rows, given hyperparameters."""

    def __init__(self, hyper: GPHyper, a_deg: FloatArray, resid_mm: FloatArray) -> None:
        self.hyper = hyper
        resid = np.asarray(resid_mm, dtype=float)
        vgs = [hyper.variogram()] * resid.shape[1]
        coords = hyper.coords(a_deg)
        self.kriging: OrdinaryKriging | LocalKriging
        if len(coords) <= DENSE_MAX_ROWS:
            self.kriging = OrdinaryKriging(coords, resid, vgs)
        else:
            self.kriging = LocalKriging(coords, resid, vgs, NEIGHBOURS)

    def predict(self, a_deg: FloatArray) -> FloatArray:
        out = self.kriging.predict(self.hyper.coords(a_deg))
        assert isinstance(out, np.ndarray)
        return out


def _rms(e: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(e) else float("nan")


@dataclass(frozen=True)
class RemainderModel:
    """The joint-space remainder model and whether it was kept (the ``remainder_model`` field)."""

    kept: bool
    tried: bool
    reason: str
    joints: list[int] = field(default_factory=list)  # 1-based joints with a length scale
    length_scales_deg: dict[str, float] = field(default_factory=dict)
    signal_rms_mm: float | None = None  # 3-D RMS of the smooth part (√(k·s))
    noise_rms_mm: float | None = None  # 3-D RMS of what it leaves as noise (√(k·σ²))
    cv_rms_mm_before: float | None = None
    cv_rms_mm_after: float | None = None
    p_value: float | None = None
    check_rms_mm_before: float | None = None
    check_rms_mm_after: float | None = None
    check_max_mm_after: float | None = None
    model: GaussianProcessRemainder | None = field(default=None, repr=False)

    @property
    def shrink_pct(self) -> float | None:
        if self.check_rms_mm_before is None or self.check_rms_mm_after is None:
            return None
        if self.check_rms_mm_before <= 0.0:
            return 0.0
        return 100.0 * (1.0 - self.check_rms_mm_after / self.check_rms_mm_before)

    @property
    def cv_gain_pct(self) -> float | None:
        if self.cv_rms_mm_before is None or self.cv_rms_mm_after is None or self.cv_rms_mm_before <= 0:
            return None
        return 100.0 * (1.0 - self.cv_rms_mm_after / self.cv_rms_mm_before)

    def to_json(self) -> dict[str, Any]:
        def r(v: float | None) -> float | None:
            return None if v is None else float(f"{v:.6g}")

        shrink, gain = self.shrink_pct, self.cv_gain_pct
        return {
            "kind": "gaussian_process",
            "tried": self.tried,
            "kept": self.kept,
            "reason": self.reason,
            "joints": self.joints,
            "length_scales_deg": {j: r(v) for j, v in self.length_scales_deg.items()},
            "signal_rms_mm": r(self.signal_rms_mm),
            "noise_rms_mm": r(self.noise_rms_mm),
            "cv_rms_mm_before": r(self.cv_rms_mm_before),
            "cv_rms_mm_after": r(self.cv_rms_mm_after),
            "cv_gain_pct": None if gain is None else round(gain, 2),
            "p_value": None if self.p_value is None else float(f"{self.p_value:.3g}"),
            "check_rms_mm_before": r(self.check_rms_mm_before),
            "check_rms_mm_after": r(self.check_rms_mm_after),
            "check_max_mm_after": r(self.check_max_mm_after),
            "shrink_pct": None if shrink is None else round(shrink, 2),
            "summary": self.describe(),
        }

    def describe(self) -> str:
        """The finding in words."""
        if not self.tried:
            return f"No joint-space remainder model was tried: {self.reason}."
        if not self.kept:
            return (
                "A joint-space remainder model (Gaussian process, one length scale per joint) did not "
                f"win out of fold ({self.reason}): no smooth function of the axis values lowers the "
                "error enough to be kept."
            )
        scales = sorted(self.length_scales_deg.items(), key=lambda kv: kv[1])[:3]
        shortest = ", ".join(f"A{j} {v:.3g}°" for j, v in scales)
        return (
            f"A joint-space remainder model took the check RMS from {self.check_rms_mm_before:.3f} to "
            f"{self.check_rms_mm_after:.3f} mm (cross-validated on the fit rows "
            f"{self.cv_rms_mm_before:.3f} → {self.cv_rms_mm_after:.3f} mm, p = {self.p_value:.2g}): "
            "structure in the axis values that no effect in the vocabulary names "
            f"(shortest length scales {shortest}). It compensates that structure without naming it."
        )


def _out_of_fold(
    lp: LinearProblem,
    cols: Sequence[int],
    a_fit: FloatArray,
    resid_fit: FloatArray,
    joints: list[int],
    seed: int,
) -> tuple[FloatArray, FloatArray, list[GPHyper]]:
    """Per fold of ``lp``: the parametric model and the remainder model fitted without it. The
    remainder (n, k) of each fit row before and after the remainder model, out of fold, and each
    fold's hyperparameters."""
    fold_resid = _fold_fits(lp, cols)
    before = np.empty_like(resid_fit)
    after = np.empty_like(resid_fit)
    hypers: list[GPHyper] = []
    for f in range(lp.k):
        test = lp.fold == f
        train = ~test
        r_train = fold_resid[f][train]
        hyper = fit_hyperparameters(a_fit[train], r_train, joints, seed=seed + f)
        hypers.append(hyper)
        gp = GaussianProcessRemainder(hyper, a_fit[train], r_train)
        before[test] = fold_resid[f][test]
        after[test] = fold_resid[f][test] - gp.predict(a_fit[test])
    return before, after, hypers


def _gain_p_value(lp: LinearProblem, before: FloatArray, after: FloatArray, n_groups: int) -> float:
    """One-sided t-test that the remainder model lowers the squared error, pose group by pose
    group (the groups are the independent units); 1 when every group gains alike."""
    gain = np.bincount(lp.cluster, weights=np.sum(before**2 - after**2, axis=1), minlength=n_groups)
    if float(np.std(gain)) > 0.0:
        return float(scipy.stats.ttest_1samp(gain, 0.0, alternative="greater").pvalue)
    return 1.0


def _pooled(hypers: list[GPHyper], joints: list[int]) -> GPHyper:
    """The folds' hyperparameters pooled: the geometric mean of each."""
    return GPHyper(
        joints=tuple(joints),
        length_deg=np.exp(np.mean([np.log(h.length_deg) for h in hypers], axis=0)),
        signal_var=float(np.exp(np.mean([math.log(h.signal_var) for h in hypers]))),
        noise_var=float(np.exp(np.mean([math.log(h.noise_var) for h in hypers]))),
    )


def _verdict(cv_before: float, cv_after: float, p_value: float, *, wins: bool, kept: bool) -> str:
    """Why the remainder model is kept or not, in words."""
    gain_pct = 100.0 * (1.0 - cv_after / cv_before) if cv_before > 0 else 0.0
    if kept:
        return f"cross-validated RMS −{gain_pct:.1f} %, p = {p_value:.2g}"
    if not wins:
        moved = f"{abs(gain_pct):.1f} % {'lower' if gain_pct >= 0 else 'higher'}"
        return f"cross-validated RMS {moved}, needs {MIN_GAIN_PCT:g} % lower"
    return f"cross-validated RMS −{gain_pct:.1f} % but p = {p_value:.2g} ≥ {ALPHA:g}"


def _fold_fits(lp: LinearProblem, cols: Sequence[int]) -> list[FloatArray]:
    """For each fold, the (n, k) residual of every fit row under ``cols`` fitted without that fold."""
    idx = np.asarray(cols, dtype=np.int64)
    out = []
    for f in range(lp.k):
        if len(idx) == 0:
            out.append(lp.r.copy())
            continue
        g = lp.gram[np.ix_(idx, idx)] - lp.fold_gram[f][np.ix_(idx, idx)]
        b = lp.jtr[idx] - lp.fold_jtr[f][idx]
        step = np.linalg.lstsq(g, b, rcond=None)[0]
        out.append(lp.r - lp.jac[:, :, idx] @ step)
    return out


def _moving_joints(a_deg: FloatArray) -> list[int]:
    return [j for j in range(a_deg.shape[1]) if float(np.ptp(a_deg[:, j])) > MIN_SPAN_DEG]


def judge_remainder(
    lp: LinearProblem,
    cols: Sequence[int],
    a_fit: FloatArray,
    resid_fit: FloatArray,
    a_check: FloatArray,
    resid_check: FloatArray,
    *,
    seed: int,
) -> RemainderModel:
    """Fit, judge out of fold and (if kept) check the joint-space remainder model.

    ``lp`` is the final parametric model's linear problem on the fit rows and ``cols`` its own
    columns (no nuisance); ``resid_fit`` / ``resid_check`` the final model's remainder (mm) on the
    fit and check rows, ``a_fit`` / ``a_check`` their axis values (deg).
    """
    n_groups = int(lp.n_clusters)
    if len(a_fit) < MIN_ROWS or n_groups < MIN_ROWS or lp.k < 2:
        return RemainderModel(False, False, f"fewer than {MIN_ROWS} fit poses")
    joints = _moving_joints(a_fit)
    if not joints:
        return RemainderModel(False, False, "no joint moves over the fit rows")
    before, after, hypers = _out_of_fold(lp, cols, a_fit, resid_fit, joints, seed)
    cv_before, cv_after = _rms(before), _rms(after)
    p_value = _gain_p_value(lp, before, after, n_groups)
    wins = cv_after < cv_before * (1.0 - MIN_GAIN_PCT / 100.0)
    kept = wins and p_value < ALPHA
    hyper = _pooled(hypers, joints)
    k = resid_fit.shape[1]
    reason = _verdict(cv_before, cv_after, p_value, wins=wins, kept=kept)
    common: dict[str, Any] = {
        "joints": [j + 1 for j in joints],
        "length_scales_deg": {str(j + 1): float(v) for j, v in zip(joints, hyper.length_deg, strict=True)},
        "signal_rms_mm": math.sqrt(k * hyper.signal_var),
        "noise_rms_mm": math.sqrt(k * hyper.noise_var),
        "cv_rms_mm_before": cv_before,
        "cv_rms_mm_after": cv_after,
        "p_value": p_value,
        "check_rms_mm_before": _rms(resid_check),
    }
    log.info("remainder_model", kept=kept, cv_before=cv_before, cv_after=cv_after, p_value=p_value)
    if not kept:
        return RemainderModel(False, True, reason, **common)
    model = GaussianProcessRemainder(hyper, a_fit, resid_fit)
    left = resid_check - model.predict(a_check)
    return RemainderModel(
        True,
        True,
        reason,
        check_rms_mm_after=_rms(left),
        check_max_mm_after=float(np.max(np.linalg.norm(left, axis=1))) if len(left) else float("nan"),
        model=model,
        **common,
    )
