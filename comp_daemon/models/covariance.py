"""Uncertainty of a parametric model's predictions: the fit's parameter covariance through the Jacobian.

A least-squares fit ``min |F(x)|²`` over the identifiable parameters ``x`` (p of them, m = 3n
residuals) leaves the parameters with the covariance ``Σ = s²·(JᵀJ)⁻¹`` (``J`` the residual's
Jacobian at the solution, ``s² = |F|²/(m − p)`` the residual variance per coordinate). A
prediction at new axis values ``A`` moves with the parameters as ``G(A) = ∂TCP/∂x`` (3 × p per
point), so its covariance is ``G Σ Gᵀ`` and the 1-σ uncertainty of each coordinate is
``sqrt(diag(G Σ Gᵀ))`` (mm). This is the uncertainty of the *model* (where the fitted robot would
put the TCP), not of a new measurement: a measured error adds the measurement noise on top.

``G`` is the fit's own Jacobian evaluated at the new rows, so the parameters are those the fit
iterated (increments of the geometric parameters from the registered nominal start, effect
values): each model's :meth:`~comp_daemon.models.base.ErrorModel.parameter_jacobian` (the kinematic
calibration's, the Chebyshev coefficients', the compliance's, the POE errors'). The inverse is
taken on scaled columns (unit norms), with singular values below 1e-14 of the largest treated as
zero (an unidentifiable direction contributes nothing instead of infinity).

Near-dependent parameters. Two parameters whose estimates are correlated beyond
:data:`NEAR_DEPENDENT_CORRELATION` (``|Σ_ij| / sqrt(Σ_ii Σ_jj)``) passed the identifiability test
but trade against each other: the data separate them only by their small differences (e.g. ``d5``
and ``alpha5`` with a probe almost on axis 6, or seed 002's ``dl4`` and ``dtheta3`` on a ballbar).
:func:`near_dependent_pairs` names every such pair, largest first; the fits report them
(``identifiability.near_dependent``) and ``fit`` prints them: fix one of the pair or measure poses
that tell them apart before trusting either value.

The covariance is saved with the model's artifact (``uncertainty``, :meth:`to_dict`) and attached
to the loaded model, whose :meth:`~comp_daemon.models.base.ErrorModel.predict_std_mm` then answers.
Kriging models have their own uncertainty, the ordinary-kriging variance of their residual.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.models.base import ErrorModel, Query

__all__ = [
    "NEAR_DEPENDENT_CORRELATION",
    "ParameterCovariance",
    "attach_covariance",
    "covariance_from_fit",
    "describe_pairs",
    "near_dependent_note",
    "near_dependent_pairs",
]

#: |correlation| of two fitted parameters above which they are reported as near-dependent
NEAR_DEPENDENT_CORRELATION = 0.9

SV_RTOL = 1e-14


def covariance_from_fit(
    jacobian: NDArray[np.float64], residual: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """``(s²·(JᵀJ)⁻¹, s)`` of a least-squares fit from its Jacobian (m, p) and residual (m,)."""
    jac = np.asarray(jacobian, dtype=float)
    res = np.asarray(residual, dtype=float)
    m, p = jac.shape
    if m <= p:
        raise ValueError(f"{m} residuals for {p} parameters: no residual variance to scale by")
    s2 = float(res @ res) / (m - p)
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    inv = np.where(sv > SV_RTOL * sv[0], 1.0 / np.where(sv > 0, sv, 1.0) ** 2, 0.0)
    scaled = (vt.T * inv) @ vt
    return s2 * scaled / np.outer(norms, norms), float(np.sqrt(s2))


def near_dependent_pairs(
    names: Sequence[str], covariance: NDArray[np.float64], threshold: float = NEAR_DEPENDENT_CORRELATION
) -> list[dict[str, Any]]:
    """``[{"pair": [a, b], "correlation": r, "condition": c}, …]`` for every pair of parameters whose
    estimates are correlated beyond ``threshold`` in absolute value, the strongest first (parameters
    with zero variance, i.e. not identified, are left out). ``c = (1 + |r|) / (1 − |r|)`` is the
    condition number of the pair's correlation matrix: how much more the pair's worst-determined
    combination (their difference, or sum) varies than its best one."""
    cov = np.asarray(covariance, dtype=float)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    ok = std > 0
    corr = np.zeros_like(cov)
    corr[np.ix_(ok, ok)] = cov[np.ix_(ok, ok)] / np.outer(std[ok], std[ok])
    i, j = np.triu_indices(len(names), k=1)
    strong = np.flatnonzero(np.abs(corr[i, j]) > threshold)
    strong = strong[np.argsort(-np.abs(corr[i[strong], j[strong]]))]
    out: list[dict[str, Any]] = []
    for k in strong:
        r = float(np.clip(corr[i[k], j[k]], -1.0, 1.0))
        pair = {"pair": [names[i[k]], names[j[k]]], "correlation": r}
        out.append({**pair, "condition": _condition(pair)})
    return out


def _condition(pair: dict[str, Any]) -> float:
    """(1 + |r|) / (1 − |r|) of a pair (:func:`near_dependent_pairs`; a stored pair may lack it)."""
    r = abs(float(pair["correlation"]))
    return float(pair.get("condition", (1.0 + r) / max(1.0 - r, 1e-15)))


def near_dependent_note(info: dict[str, Any]) -> str | None:
    """The sentence a command prints for a fit's ``identifiability.near_dependent`` pairs, or None."""
    pairs = (info.get("identifiability") or {}).get("near_dependent") or []
    if not pairs:
        return None
    return (
        f"near-dependent parameters (|correlation| > {NEAR_DEPENDENT_CORRELATION:g}; fitted, but each "
        f"trades against the other): {describe_pairs(pairs)}; fix one of a pair or add poses that tell "
        "them apart before trusting their values"
    )


def describe_pairs(pairs: Sequence[dict[str, Any]], limit: int = 6) -> str:
    """``d5 ~ alpha5 (r -0.998, condition 999), …`` of :func:`near_dependent_pairs` (the first ``limit``)."""
    text = ", ".join(
        f"{p['pair'][0]} ~ {p['pair'][1]} (r {p['correlation']:+.3f}, condition {_condition(p):.3g})"
        for p in pairs[:limit]
    )
    return text + (f" and {len(pairs) - limit} more" if len(pairs) > limit else "")


@dataclass(frozen=True, slots=True)
class ParameterCovariance:
    """The identified parameters of a fit, their values and covariance (module docstring)."""

    names: tuple[str, ...]
    values: NDArray[np.float64]  # (p,) as the fit iterated them
    covariance: NDArray[np.float64]  # (p, p)
    sigma_mm: float  # s: the fit's residual standard deviation per coordinate
    rows: int

    def __post_init__(self) -> None:
        p = len(self.names)
        values = np.asarray(self.values, dtype=float)
        cov = np.asarray(self.covariance, dtype=float)
        if values.shape != (p,) or cov.shape != (p, p):
            raise ValueError(f"uncertainty: {p} names need ({p},) values and a ({p}, {p}) covariance")
        if not (np.all(np.isfinite(values)) and np.all(np.isfinite(cov))):
            raise ValueError("uncertainty: values and covariance must be finite")
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "covariance", cov)

    @classmethod
    def of_fit(
        cls,
        names: Sequence[str],
        values: NDArray[np.float64],
        jacobian: NDArray[np.float64],
        residual: NDArray[np.float64],
    ) -> ParameterCovariance:
        cov, s = covariance_from_fit(jacobian, residual)
        return cls(tuple(names), np.asarray(values, dtype=float), cov, s, int(np.asarray(residual).size // 3))

    def std_mm(self, model: ErrorModel, query: Query) -> NDArray[np.float64]:
        """(n, 3) 1-σ uncertainty (mm) of ``model``'s predicted TCP at the query's poses."""
        g = model.parameter_jacobian(self.names, self.values, query)  # (n, 3, p)
        var = np.einsum("nip,pq,niq->ni", g, self.covariance, g)
        return np.sqrt(np.maximum(var, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": "s^2 (J^T J)^-1 of the fit on its identifiable parameters, through the Jacobian",
            "names": list(self.names),
            "values": self.values.tolist(),
            "covariance": self.covariance.tolist(),
            "sigma_mm": self.sigma_mm,
            "rows": self.rows,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ParameterCovariance:
        return cls(
            tuple(data["names"]),
            np.array(data["values"], dtype=float),
            np.array(data["covariance"], dtype=float),
            float(data["sigma_mm"]),
            int(data["rows"]),
        )


def attach_covariance(
    model: ErrorModel,
    names: Sequence[str],
    values: NDArray[np.float64],
    jacobian: NDArray[np.float64],
    residual: NDArray[np.float64],
) -> ParameterCovariance | None:
    """Set ``model.uncertainty`` from a fit (None, and nothing set, when the fit has no residual
    degrees of freedom)."""
    if np.asarray(jacobian).shape[0] <= np.asarray(jacobian).shape[1]:
        return None
    cov = ParameterCovariance.of_fit(names, values, jacobian, residual)
    model.uncertainty = cov
    return cov
