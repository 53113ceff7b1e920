"""Semivariograms of positioning error vs distance (seed 001 §2.1, eqs 12–13), empirical and fitted.

The semivariogram of a field ``z`` (here one component of the positioning error, mm) is half the
variance of the increment between two points ``h`` apart: ``γ(h) = ½·E[(z(x) − z(x+h))²]``. Its
empirical estimate (Matheron's, seed 001 eq. 12) over the pairs whose distance falls in bin k is::

    γ̂(h_k) = 1 / (2·N(h_k)) · Σ_{(i,j) ∈ bin k} (z_i − z_j)²

with ``h_k`` the mean distance of those pairs and ``N(h_k)`` their number. Seed 001 splits the lag
range into 12 equal bins (Fig. 4); that is the default. Small γ at small lags means "nearby states
have similar errors" (error similarity); a large value at the first bins (a nugget) means they do
not.

Distances are whatever the caller's coordinates make them: the joint-space distance of seed 001 is
the Euclidean distance of axis values in deg (see :mod:`comp_daemon.models.kriging` for the
direction-aware version). Units: ``h`` in the coordinates' unit, ``γ`` in the value unit squared
(mm²). Values may have several components (n, k); every component gets its own γ̂ column.

Fitted models (``nugget`` c0, partial sill c, range a; ``γ(0) = 0``, for h > 0)::

    spherical    γ = c0 + c·(1.5·h/a − 0.5·(h/a)³)  for h < a,  c0 + c beyond
    exponential  γ = c0 + c·(1 − exp(−3h/a))         (a = practical range, 95 % of the sill)
    gaussian     γ = c0 + c·(1 − exp(−3h²/a²))       (a = practical range)

The correlation of the structured part is ``ρ(h) = 1 − (γ(h) − c0)/c`` for h > 0, ``ρ(0) = 1``.
The spherical model is a valid covariance only up to three dimensions; in joint space (6 or more
coordinates) only the exponential and Gaussian models are (:func:`valid_models`).

Fitting is weighted least squares on the bins, with Cressie's weights ``N(h_k)/γ(h_k)²`` (the
default) or the pair counts ``N(h_k)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.bounded_lsq import trf_fit, trf_fit_batch

__all__ = [
    "VARIOGRAM_MAX_PAIRS",
    "VARIOGRAM_MODELS",
    "EmpiricalVariogram",
    "JointStatePairs",
    "VariogramModel",
    "binned_semivariogram",
    "empirical_semivariogram",
    "fit_variogram",
    "fit_variograms",
    "pairwise_distances",
    "valid_models",
]

VARIOGRAM_MODELS: tuple[str, ...] = ("spherical", "exponential", "gaussian")
VARIOGRAM_MAX_PAIRS = 200_000  # JointStatePairs: sample pairs drawn when there are more
Weighting = Literal["cressie", "npairs"]
FitMethod = Literal["batch", "each"]
FIT_METHOD: FitMethod = "batch"  # how fit_variograms solves its problems unless told (see there)
START_RANGES = (0.15, 0.35, 0.7, 1.5)  # a fit's starting ranges, fractions of the largest lag


def valid_models(dim: int) -> tuple[str, ...]:
    """The variogram models that are valid (conditionally negative definite) in ``dim`` dimensions."""
    return VARIOGRAM_MODELS if dim <= 3 else ("exponential", "gaussian")


def pairwise_distances(x: NDArray[np.float64], y: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """(n, m) Euclidean distances between the rows of ``x`` (n, d) and ``y`` (m, d) (``y = x`` if None)."""
    x = np.asarray(x, dtype=float)
    yy = x if y is None else np.asarray(y, dtype=float)
    if x.ndim != 2 or yy.ndim != 2 or x.shape[1] != yy.shape[1]:
        raise ValueError(f"coordinates must be (n, d) and (m, d), got {x.shape} and {yy.shape}")
    # |x|² + |y|² − 2 x·y is fast but loses digits for near points; refine with the exact
    # difference only where that matters (distances below 1e-4 of the coordinate scale)
    sq = np.einsum("ij,ij->i", x, x)[:, None] + np.einsum("ij,ij->i", yy, yy)[None, :] - 2.0 * (x @ yy.T)
    np.maximum(sq, 0.0, out=sq)
    d = np.sqrt(sq)
    scale = max(float(np.abs(x).max(initial=0.0)), float(np.abs(yy).max(initial=0.0)), 1e-300)
    near = np.argwhere(d < 1e-4 * scale)
    if near.size:
        i, j = near[:, 0], near[:, 1]
        d[i, j] = np.linalg.norm(x[i] - yy[j], axis=1)
    if y is None:
        np.fill_diagonal(d, 0.0)
    return d


@dataclass(frozen=True, slots=True)
class VariogramModel:
    """A fitted semivariogram: ``kind``, ``nugget`` and ``psill`` (value unit²), ``range`` (distance unit)."""

    kind: str
    nugget: float
    psill: float
    range: float

    def __post_init__(self) -> None:
        if self.kind not in VARIOGRAM_MODELS:
            raise ValueError(f"variogram kind '{self.kind}' unknown (known: {', '.join(VARIOGRAM_MODELS)})")
        for name in ("nugget", "psill", "range"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise ValueError(f"variogram {name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if self.nugget < 0.0:
            raise ValueError(f"variogram nugget must be >= 0, got {self.nugget}")
        if self.psill <= 0.0:
            raise ValueError(f"variogram partial sill must be > 0, got {self.psill}")
        if self.range <= 0.0:
            raise ValueError(f"variogram range must be > 0, got {self.range}")

    @property
    def sill(self) -> float:
        return self.nugget + self.psill

    def correlation(self, h: NDArray[np.float64]) -> NDArray[np.float64]:
        """ρ(h) of the structured part (1 at h = 0, → 0 far away); ``h`` any shape."""
        return _correlation(self.kind, np.asarray(h, dtype=float), self.range)

    def correlation_of_squared(
        self, h2: NDArray[np.float64], out: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """ρ at the squared distances ``h2`` (the Gaussian model needs no square root), written
        into ``out`` when given (any shape matching ``h2``)."""
        h2 = np.asarray(h2, dtype=float)
        if out is None:
            out = np.empty_like(h2)
        if self.kind == "gaussian":
            np.multiply(h2, -3.0 / (self.range * self.range), out=out)
        elif self.kind == "exponential":
            np.sqrt(h2, out=out)
            out *= -3.0 / self.range
        else:
            out[...] = _correlation(self.kind, np.sqrt(h2), self.range)
            return out
        return np.exp(out, out=out)

    def gamma(self, h: NDArray[np.float64]) -> NDArray[np.float64]:
        """γ(h) (value unit²); 0 at h = 0, ``nugget + psill·(1 − ρ(h))`` for h > 0."""
        h = np.asarray(h, dtype=float)
        out = self.nugget + self.psill * (1.0 - self.correlation(h))
        return np.where(h > 0.0, out, 0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "nugget": self.nugget, "psill": self.psill, "range": self.range}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VariogramModel:
        try:
            return cls(str(data["kind"]), float(data["nugget"]), float(data["psill"]), float(data["range"]))
        except KeyError as exc:
            raise ValueError(f"variogram model: missing field {exc.args[0]!r}") from None


def _correlation(kind: str, h: NDArray[np.float64], a: float) -> NDArray[np.float64]:
    r = np.abs(np.asarray(h, dtype=float))
    r /= a
    if kind == "spherical":
        return np.where(r < 1.0, 1.0 - 1.5 * r + 0.5 * r**3, 0.0)
    if np.ndim(r) == 0:
        return np.exp(-3.0 * r) if kind == "exponential" else np.exp(-3.0 * r * r)
    # a kriging system's whole distance matrix: the same operations in place, without temporaries
    if kind == "exponential":
        r *= -3.0
        return np.exp(r, out=r)
    g = r * -3.0
    g *= r
    return np.exp(g, out=g)


def _correlation_da(
    kind: str, h: NDArray[np.float64], a: float, rho: NDArray[np.float64]
) -> NDArray[np.float64]:
    """∂ρ/∂a of :func:`_correlation` at ``h`` (``rho`` its value there)."""
    r = np.abs(h) / a
    if kind == "spherical":
        return np.where(r < 1.0, 1.5 * (1.0 - r * r) * r / a, 0.0)
    if kind == "exponential":
        return rho * 3.0 * r / a
    return rho * 6.0 * r * r / a


@dataclass(frozen=True, slots=True)
class EmpiricalVariogram:
    """Binned semivariance: per bin the mean lag, γ̂ per component (k columns) and the pair count."""

    edges: NDArray[np.float64]  # (n_bins + 1,)
    lag: NDArray[np.float64]  # (n_bins,) mean pair distance in the bin (bin centre if empty)
    gamma: NDArray[np.float64]  # (n_bins, k) semivariance, NaN where the bin is empty
    count: NDArray[np.int64]  # (n_bins,) number of pairs

    @property
    def n_components(self) -> int:
        return int(self.gamma.shape[1])

    def to_dict(self) -> dict[str, Any]:
        return {
            "edges": self.edges.tolist(),
            "lag": self.lag.tolist(),
            "gamma": [[None if not np.isfinite(v) else float(v) for v in row] for row in self.gamma],
            "count": self.count.tolist(),
        }


def empirical_semivariogram(
    coords: NDArray[np.float64] | None,
    values: NDArray[np.float64],
    *,
    n_bins: int = 12,
    max_lag: float | None = None,
    distances: NDArray[np.float64] | None = None,
) -> EmpiricalVariogram:
    """Seed 001 eq. 12 over all pairs of the n points, in ``n_bins`` equal bins of ``[0, max_lag]``.

    ``coords`` (n, d) or precomputed ``distances`` (n, n); ``values`` (n,) or (n, k). ``max_lag``
    defaults to half the largest pair distance (pairs farther apart are few and say nothing about
    similarity; seed 001's Fig. 4 bins the whole range: pass ``max_lag=np.inf`` for that).
    """
    z = np.asarray(values, dtype=float)
    if z.ndim == 1:
        z = z[:, None]
    if z.ndim != 2:
        raise ValueError(f"values must be (n,) or (n, k), got shape {np.shape(values)}")
    n = z.shape[0]
    if n < 2:
        raise ValueError(f"a semivariogram needs at least 2 points, got {n}")
    if not np.all(np.isfinite(z)):
        raise ValueError("values must be finite")
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    if distances is None:
        if coords is None:
            raise ValueError("give coords or distances")
        dist = pairwise_distances(np.asarray(coords, dtype=float))
    else:
        dist = np.asarray(distances, dtype=float)
    if dist.shape != (n, n):
        raise ValueError(f"distances must be ({n}, {n}) for {n} values, got {dist.shape}")
    iu, ju = np.triu_indices(n, k=1)
    return binned_semivariogram(dist[iu, ju], 0.5 * (z[iu] - z[ju]) ** 2, n_bins=n_bins, max_lag=max_lag)


def binned_semivariogram(
    h: NDArray[np.float64],
    half_sq: NDArray[np.float64],
    *,
    n_bins: int = 12,
    max_lag: float | None = None,
) -> EmpiricalVariogram:
    """Seed 001 eq. 12 from the pairs themselves: their distances ``h`` (p,) and half squared
    increments ``½(z_i − z_j)²`` (p, k); ``max_lag`` as :func:`empirical_semivariogram`.

    A caller that tries several metrics on the same samples computes the increments once.
    """
    h = np.asarray(h, dtype=float)
    sq = np.asarray(half_sq, dtype=float)
    if sq.ndim == 1:
        sq = sq[:, None]
    if h.ndim != 1 or sq.shape[0] != h.shape[0] or h.size == 0:
        raise ValueError(f"pair distances (p,) and increments (p, k) must match, got {h.shape}, {sq.shape}")
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    hmax = float(h.max())
    top = 0.5 * hmax if max_lag is None else min(float(max_lag), hmax)
    if not top > 0.0:
        raise ValueError("max_lag must be > 0 (are all points identical?)")
    edges = np.linspace(0.0, top, n_bins + 1)
    keep = h <= top
    if not keep.all():
        h, sq = h[keep], sq[keep]
    b = np.minimum(np.searchsorted(edges, h, side="right") - 1, n_bins - 1)
    b = np.maximum(b, 0)
    count = np.bincount(b, minlength=n_bins).astype(np.int64)
    sums = np.stack([np.bincount(b, weights=sq[:, c], minlength=n_bins) for c in range(sq.shape[1])], axis=1)
    hsum = np.bincount(b, weights=h, minlength=n_bins)
    filled = count > 0
    gamma = np.full(sums.shape, np.nan)
    gamma[filled] = sums[filled] / count[filled, None]
    lag = 0.5 * (edges[:-1] + edges[1:])
    lag[filled] = hsum[filled] / count[filled]
    return EmpiricalVariogram(edges=edges, lag=lag, gamma=gamma, count=count)


def _bounds_and_starts(
    lag: NDArray[np.float64], gam: NDArray[np.float64], nugget: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The parameter bounds ((c0,) c, a) of a fit to the bins and its four starting points (4, n)."""
    gmax = max(float(gam.max()), 1e-300)
    hmax = float(lag.max())
    lo = np.array([0.0, 1e-9 * gmax, 1e-3 * hmax])
    hi = np.array([gmax, 4.0 * gmax, 4.0 * hmax])
    if not nugget:
        lo, hi = lo[1:], hi[1:]
    c0_start = 0.5 * float(gam[0])
    starts = []
    for frac in START_RANGES:
        start = [c0_start, max(gmax - c0_start, 2.0 * lo[-2]), frac * hmax]
        p0 = np.array(start if nugget else start[1:])
        starts.append(np.clip(p0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo)))
    return lo, hi, np.array(starts)


def _fit_one(
    kind: str,
    lag: NDArray[np.float64],
    gam: NDArray[np.float64],
    cnt: NDArray[np.float64],
    weighting: Weighting,
    nugget: bool,
) -> tuple[VariogramModel, float]:
    """Best fit of one model kind from a few starting ranges, one problem at a time (the
    ``"each"`` method); returns the model and its cost."""
    gmax = max(float(gam.max()), 1e-300)
    floor = 1e-12 * gmax

    def split(p: NDArray[np.float64]) -> tuple[float, float, float]:
        return (float(p[0]), float(p[1]), float(p[2])) if nugget else (0.0, float(p[0]), float(p[1]))

    sqrt_cnt = np.sqrt(cnt)

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        c0, c, a = split(p)
        g = c0 + c * (1.0 - _correlation(kind, lag, a))
        if weighting == "cressie":
            return sqrt_cnt * (gam / np.maximum(g, floor) - 1.0)
        return sqrt_cnt * (g - gam) / gmax

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        c0, c, a = split(p)
        rho = _correlation(kind, lag, a)
        dg = np.stack([np.ones_like(lag), 1.0 - rho, -c * _correlation_da(kind, lag, a, rho)], axis=1)
        if not nugget:
            dg = dg[:, 1:]
        if weighting == "cressie":
            g = c0 + c * (1.0 - rho)
            scale = np.where(g > floor, -sqrt_cnt * gam / np.maximum(g, floor) ** 2, 0.0)
            return scale[:, None] * dg
        return (sqrt_cnt / gmax)[:, None] * dg

    lo, hi, starts = _bounds_and_starts(lag, gam, nugget)
    best: tuple[float, NDArray[np.float64]] | None = None
    for p0 in starts:
        # scipy.optimize.least_squares(method="trf", x_scale="jac"), without its per-call cost
        x, cost = trf_fit(resid, jac, p0, lo, hi)
        if best is None or cost < best[0]:
            best = (cost, x)
    assert best is not None
    c0, c, a = split(best[1])
    return VariogramModel(kind, c0, c, a), best[0]


def _fit_batch(
    bins: Sequence[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
    kinds: tuple[str, ...],
    weighting: Weighting,
    nugget: bool,
) -> list[VariogramModel]:
    """The best fit to each series of bins (lag, γ̂, count) among ``kinds``: every kind and
    starting range of every series one problem of a single :func:`trf_fit_batch` (the ``"batch"``
    method); the same problems, starts and choice (the lowest cost, the first on a tie) as
    :func:`_fit_one`."""
    n_starts = len(START_RANGES)
    per_series = len(kinds) * n_starts
    width = max(lag.size for lag, _, _ in bins)
    n_lanes = len(bins) * per_series
    lag_b, gam_b, w_b = np.empty((n_lanes, width)), np.empty((n_lanes, width)), np.zeros((n_lanes, width))
    gmax_b, m_b = np.empty(n_lanes), np.empty(n_lanes, dtype=np.intp)
    kind_b = np.empty(n_lanes, dtype=np.intp)
    n_par = 3 if nugget else 2
    x0, lo, hi = np.empty((n_lanes, n_par)), np.empty((n_lanes, n_par)), np.empty((n_lanes, n_par))
    for i, (lag, gam, cnt) in enumerate(bins):
        lanes = slice(i * per_series, (i + 1) * per_series)
        m = lag.size  # shorter series pad with their last bin at zero weight
        lag_b[lanes] = np.concatenate([lag, np.full(width - m, lag[-1])])
        gam_b[lanes] = np.concatenate([gam, np.full(width - m, gam[-1])])
        w_b[lanes, :m] = np.sqrt(cnt)
        gmax_b[lanes], m_b[lanes] = max(float(gam.max()), 1e-300), m
        kind_b[lanes] = np.repeat([VARIOGRAM_MODELS.index(k) for k in kinds], n_starts)
        b_lo, b_hi, starts = _bounds_and_starts(lag, gam, nugget)
        lo[lanes], hi[lanes], x0[lanes] = b_lo, b_hi, np.tile(starts, (len(kinds), 1))
    floor_b = 1e-12 * gmax_b
    gauss_b = kind_b == VARIOGRAM_MODELS.index("gaussian")
    spherical_b = kind_b == VARIOGRAM_MODELS.index("spherical")
    any_spherical = bool(spherical_b.any())

    def parts(p: NDArray[np.float64], rows: NDArray[np.intp]) -> tuple[NDArray[np.float64], ...]:
        """c0, c, a (k, 1), the reduced lags r = h/a and ρ (k, M) of the problems ``rows``."""
        c0 = p[:, :1] if nugget else np.zeros((p.shape[0], 1))
        c, a = p[:, -2:-1], p[:, -1:]
        r = np.abs(lag_b[rows]) / a
        rho = np.exp(-3.0 * r * np.where(gauss_b[rows, None], r, 1.0))
        if any_spherical:
            rho = np.where(spherical_b[rows, None], np.where(r < 1.0, 1.0 - 1.5 * r + 0.5 * r**3, 0.0), rho)
        return c0, c, a, r, rho

    def resid(p: NDArray[np.float64], rows: NDArray[np.intp]) -> NDArray[np.float64]:
        c0, c, _, _, rho = parts(p, rows)
        g = c0 + c * (1.0 - rho)
        if weighting == "cressie":
            return w_b[rows] * (gam_b[rows] / np.maximum(g, floor_b[rows, None]) - 1.0)
        return w_b[rows] * (g - gam_b[rows]) / gmax_b[rows, None]

    def jac(p: NDArray[np.float64], rows: NDArray[np.intp]) -> NDArray[np.float64]:
        c0, c, a, r, rho = parts(p, rows)
        drho = np.where(gauss_b[rows, None], rho * 6.0 * r * r / a, rho * 3.0 * r / a)
        if any_spherical:
            drho = np.where(
                spherical_b[rows, None], np.where(r < 1.0, 1.5 * (1.0 - r * r) * r / a, 0.0), drho
            )
        dg = np.stack([np.ones_like(rho), 1.0 - rho, -c * drho], axis=2)[:, :, 3 - n_par :]
        if weighting == "cressie":
            g = c0 + c * (1.0 - rho)
            floor = floor_b[rows, None]
            scale = np.where(g > floor, -w_b[rows] * gam_b[rows] / np.maximum(g, floor) ** 2, 0.0)
            return scale[:, :, None] * dg
        return (w_b[rows] / gmax_b[rows, None])[:, :, None] * dg

    x, cost = trf_fit_batch(resid, jac, x0, lo, hi, m_b)
    out = []
    for i in range(len(bins)):
        lane = i * per_series + int(np.argmin(cost[i * per_series : (i + 1) * per_series]))
        p = x[lane]
        c0, c, a = (float(p[0]), float(p[1]), float(p[2])) if nugget else (0.0, float(p[0]), float(p[1]))
        out.append(VariogramModel(VARIOGRAM_MODELS[kind_b[lane]], c0, c, a))
    return out


def _kinds(kind: str | Sequence[str], dim: int | None) -> tuple[str, ...]:
    """The model kinds a fit tries (see :func:`fit_variogram`), checked."""
    if isinstance(kind, str):
        kinds: tuple[str, ...] = (
            (valid_models(dim) if dim is not None else VARIOGRAM_MODELS) if kind == "auto" else (kind,)
        )
    else:
        kinds = tuple(kind)
    for k in kinds:
        if k not in VARIOGRAM_MODELS:
            raise ValueError(f"variogram kind '{k}' unknown (known: {', '.join(VARIOGRAM_MODELS)})")
        if dim is not None and k not in valid_models(dim):
            raise ValueError(f"the {k} model is not a valid variogram in {dim} dimensions")
    return kinds


def _bins(
    emp: EmpiricalVariogram, component: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The non-empty bins of one component: lag, γ̂ and pair count (ValueError if too few)."""
    if not 0 <= component < emp.n_components:
        raise ValueError(f"component {component} out of range (the variogram has {emp.n_components})")
    g = emp.gamma[:, component]
    ok = (emp.count > 0) & np.isfinite(g)
    if int(ok.sum()) < 3:
        raise ValueError(f"need at least 3 non-empty bins to fit a variogram, got {int(ok.sum())}")
    lag, gam, cnt = emp.lag[ok], g[ok], emp.count[ok].astype(float)
    if not float(gam.max()) > 0.0:
        raise ValueError("the values do not vary: the semivariogram is zero everywhere")
    return lag, gam, cnt


def _fit_series(
    bins: Sequence[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
    kinds: tuple[str, ...],
    weighting: Weighting,
    nugget: bool,
    method: FitMethod | None,
) -> list[VariogramModel]:
    """The best model of ``kinds`` for each series of bins, by ``method`` (see :func:`fit_variograms`)."""
    if weighting not in ("cressie", "npairs"):
        raise ValueError(f"weighting must be 'cressie' or 'npairs', got {weighting!r}")
    method = FIT_METHOD if method is None else method
    if method == "batch":
        return _fit_batch(bins, kinds, weighting, nugget)
    if method != "each":
        raise ValueError(f"variogram fit method must be 'batch' or 'each', got {method!r}")
    fits = [[_fit_one(k, lag, gam, cnt, weighting, nugget) for k in kinds] for lag, gam, cnt in bins]
    return [min(f, key=lambda kc: kc[1])[0] for f in fits]


def fit_variograms(
    emps: Sequence[EmpiricalVariogram],
    *,
    kind: str | Sequence[str] = "auto",
    dim: int | None = None,
    nugget: bool = True,
    weighting: Weighting = "cressie",
    method: FitMethod | None = None,
) -> list[list[VariogramModel]]:
    """:func:`fit_variogram` of every component of every empirical variogram: per variogram, one
    model per component.

    ``method``: ``"batch"`` solves all their problems (each kind from each starting range) together
    (:func:`comp_daemon.estimation.bounded_lsq.trf_fit_batch`); ``"each"`` one after the other with
    :func:`comp_daemon.estimation.bounded_lsq.trf_fit`, the reference the batch is tested against
    (the same choices and models, to rounding where the bins leave a model undetermined). None:
    :data:`FIT_METHOD`.
    """
    kinds = _kinds(kind, dim)
    bins = [_bins(e, c) for e in emps for c in range(e.n_components)]
    flat = iter(_fit_series(bins, kinds, weighting, nugget, method))
    return [[next(flat) for _ in range(e.n_components)] for e in emps]


def fit_variogram(
    emp: EmpiricalVariogram,
    component: int = 0,
    *,
    kind: str | Sequence[str] = "auto",
    dim: int | None = None,
    nugget: bool = True,
    weighting: Weighting = "cressie",
    method: FitMethod | None = None,
) -> VariogramModel:
    """Fit a model to one component of an empirical semivariogram (weighted least squares).

    ``kind``: one of :data:`VARIOGRAM_MODELS`, a list of them, or ``"auto"`` — every model valid in
    ``dim`` dimensions (all three if ``dim`` is None), the one with the lowest weighted residual wins.
    ``nugget=False`` fixes the nugget at 0. Each kind is fitted from the starting ranges
    :data:`START_RANGES` (fractions of the largest lag); ``method`` as :func:`fit_variograms`.
    """
    bins = _bins(emp, component)
    return _fit_series([bins], _kinds(kind, dim), weighting, nugget, method)[0]


class JointStatePairs:
    """Sample pairs of joint states for empirical variograms under several metrics.

    Every pair of the n samples, or :data:`VARIOGRAM_MAX_PAIRS` of them drawn reproducibly from all
    n: per pair the squared axis-value differences (deg², per joint), the squared differences of the
    approach directions (0, 1 or 4 per joint) and the half squared residual increments. The
    distance under joint weights ``w`` and direction separations ``ρ`` (the metric of
    :class:`comp_daemon.models.kriging.JointStateMetric`) is then ``√(Σ w²ΔA² + Σ ρ²·Δdir²/4)``,
    one product per metric, without embedding the samples again.
    """

    def __init__(
        self, a_deg: NDArray[np.float64], dir: NDArray[np.float64] | None, values: NDArray[np.float64]
    ) -> None:
        n = a_deg.shape[0]
        if n * (n - 1) // 2 <= VARIOGRAM_MAX_PAIRS:
            i, j = np.triu_indices(n, k=1)
        else:
            rng = np.random.default_rng(1)
            i = rng.integers(0, n, VARIOGRAM_MAX_PAIRS)
            j = (i + rng.integers(1, n, VARIOGRAM_MAX_PAIRS)) % n  # never i itself
        self.da2 = (a_deg[i] - a_deg[j]) ** 2  # (p, 6)
        self.ddir2 = None if dir is None else (dir[i] - dir[j]) ** 2  # (p, 6)
        self.half_sq = 0.5 * (values[i] - values[j]) ** 2  # (p, k)

    def semivariogram(
        self,
        joint_weights: NDArray[np.float64],
        dir_separation_deg: NDArray[np.float64],
        n_bins: int,
        max_lag: float | None,
    ) -> EmpiricalVariogram:
        h2 = self.da2 @ (np.asarray(joint_weights, dtype=float) ** 2)
        sep = np.asarray(dir_separation_deg, dtype=float)
        if self.ddir2 is not None and np.any(sep > 0.0):
            h2 += self.ddir2 @ (0.25 * sep**2)
        return binned_semivariogram(np.sqrt(h2), self.half_sq, n_bins=n_bins, max_lag=max_lag)
