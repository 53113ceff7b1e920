"""Measurement uncertainty from repeats, weights, and the nested correction (seed 002, spec A.8).

Each sample k is measured n times; the last repeat is the reading ``L_a,k`` (as in the paper), or
the mean when ``reading="mean"``. Type A uncertainty (eq. 34, reconstructed)::

    L̄_k = mean_r L_k,r ;  u_k = sqrt(Σ_r (L_k,r − L̄_k)² / (n − 1)) ;  b_k = z·u_k,  z = 1.96 (95 %)

With ``reading="mean"`` the uncertainty of the reading is ``u_k/√n``. Weights for a weighted fit are
``w_k = 1/max(u_k, u_floor)²`` with ``u_floor`` = 0.5 µm (a product extension; the paper does not
weight).

Nested correction (eqs 35–36, reconstructed). ``a_k = L_a,k − L_t,k(x̂)`` is the part of the reading
the current model does not explain. Its band decides a factor c::

    b/2 ≤ |a| ≤ b  →  c = 2 ;   b/4 < |a| < b/2  →  c = 4 ;   |a| ≤ b/4  →  no correction
    |a| > b        →  no correction, flagged as a model error rather than noise

and the corrected reading is ``L_t + a_n`` with ``a_n = a − sgn(a)·b/c`` (``rule="step"``, the
quantised step of the paper's "quantified nested algorithm"); ``"divide"`` (``a/c``) and
``"subtract"`` (``a − a/c``) are the alternatives. :func:`nested_identification` alternates
identification and correction until the fit is below ``h_target`` with every residual within
``b/4``, nothing changes, or ``max_rounds``. The correction pulls readings toward the model inside
their noise band: it lowers the fit residual by construction but adds no information — judge it on
check data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger

__all__ = [
    "Z_95",
    "NestedResult",
    "NestedRound",
    "RepeatUncertainty",
    "covariance_scale",
    "nested_correction",
    "nested_factor",
    "nested_identification",
    "prediction_std",
    "repeat_uncertainty",
    "weights_from_uncertainty",
]

_log = get_logger(__name__)

Z_95 = 1.96
U_FLOOR_MM = 0.5e-3
Rule = Literal["step", "divide", "subtract"]


@dataclass(frozen=True, slots=True)
class RepeatUncertainty:
    """Per sample: the reading, the mean of the repeats, standard (u) and expanded (b) uncertainty."""

    reading: NDArray[np.float64]
    mean: NDArray[np.float64]
    u: NDArray[np.float64]
    b: NDArray[np.float64]
    n_repeats: int


def repeat_uncertainty(
    repeats: NDArray[np.float64], *, z: float = Z_95, reading: Literal["last", "mean"] = "last"
) -> RepeatUncertainty:
    """Type A uncertainty of each row of ``repeats`` (k samples, n ≥ 2 repeats each)."""
    r = np.atleast_2d(np.asarray(repeats, dtype=float))
    n = r.shape[1]
    if n < 2:
        raise ValueError(f"uncertainty from repeats needs at least 2 repeats per sample, got {n}")
    mean = r.mean(axis=1)
    u = r.std(axis=1, ddof=1)
    if reading == "mean":
        u = u / np.sqrt(n)
        value = mean
    else:
        value = r[:, -1]
    return RepeatUncertainty(reading=value, mean=mean, u=u, b=z * u, n_repeats=n)


def weights_from_uncertainty(u: NDArray[np.float64], floor: float = U_FLOOR_MM) -> NDArray[np.float64]:
    """``1/max(u, floor)²``: inverse-variance weights (units of 1/u²)."""
    return np.asarray(1.0 / np.maximum(np.asarray(u, dtype=float), floor) ** 2)


def covariance_scale(
    weights: NDArray[np.float64], residual: NDArray[np.float64], n_fitted: int
) -> tuple[float, float]:
    """The reduced χ² of a weighted fit, Σ w·r² / (n − p) (ν at least 1), and the factor its
    covariance (JᵀWJ)⁻¹ takes: χ²/ν where the model does not explain the readings to their
    uncertainty (χ²/ν > 1), else 1 — the measurement uncertainty alone never narrows it."""
    chi2_nu = float(np.sum(weights * residual**2)) / max(residual.size - n_fitted, 1)
    return chi2_nu, max(1.0, chi2_nu)


def nested_factor(
    a: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """The factor c (2, 4, or 0 for no correction) of each residual, and which are flagged (|a| > b)."""
    mag = np.abs(np.asarray(a, dtype=float))
    bb = np.asarray(b, dtype=float)
    c = np.zeros(mag.shape, dtype=np.intp)
    c[(mag >= bb / 2) & (mag <= bb)] = 2
    c[(mag > bb / 4) & (mag < bb / 2)] = 4
    return c, np.asarray(mag > bb)


def nested_correction(
    a: NDArray[np.float64], b: NDArray[np.float64], rule: Rule = "step"
) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.bool_]]:
    """Corrected residuals ``a_n``, the factors used and the flagged ones (module docstring)."""
    aa = np.asarray(a, dtype=float)
    bb = np.broadcast_to(np.asarray(b, dtype=float), aa.shape)
    c, flagged = nested_factor(aa, bb)
    cf = np.where(c > 0, c, 1).astype(float)
    if rule == "step":
        corrected = aa - np.sign(aa) * bb / cf
    elif rule == "divide":
        corrected = aa / cf
    elif rule == "subtract":
        corrected = aa - aa / cf
    else:
        raise ValueError(f"unknown rule {rule!r} (step, divide, subtract)")
    return np.where(c > 0, corrected, aa), c, flagged


@dataclass(frozen=True, slots=True)
class NestedRound:
    """One round: the fit's RMS residual before correcting, readings corrected, their mean shift."""

    h: float
    n_corrected: int
    mean_shift: float


@dataclass(frozen=True, slots=True)
class NestedResult:
    theta: NDArray[np.float64]
    readings: NDArray[np.float64]  # corrected readings
    residual: NDArray[np.float64]  # final a = readings − prediction
    flagged: NDArray[np.bool_]  # |a| > b in the last round: model error, not noise
    rounds: tuple[NestedRound, ...]
    reason: str  # converged | unchanged | max_rounds


def nested_identification(
    identify: Callable[[NDArray[np.float64], NDArray[np.float64] | None], NDArray[np.float64]],
    predict: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    readings: NDArray[np.float64],
    b: NDArray[np.float64],
    *,
    rule: Rule = "step",
    h_target: float = 0.02,
    max_rounds: int = 10,
) -> NestedResult:
    """Alternate ``identify(readings, warm_start) -> theta`` and the nested correction of the readings.

    ``predict(theta)`` gives the model's values of the readings (e.g. ballbar lengths).
    """
    values = np.array(readings, dtype=float, copy=True)
    theta = identify(values, None)
    rounds: list[NestedRound] = []
    reason = "max_rounds"
    for _ in range(max_rounds):
        pred = predict(theta)
        a = values - pred
        h = float(np.sqrt(np.mean(a**2)))
        a_new, c, _ = nested_correction(a, b, rule)
        changed = c > 0
        if h < h_target and not np.any(changed):
            reason = "converged"
            rounds.append(NestedRound(h, 0, 0.0))
            break
        if not np.any(changed):
            reason = "unchanged"
            rounds.append(NestedRound(h, 0, 0.0))
            break
        shift = a_new - a
        values = pred + a_new
        rounds.append(NestedRound(h, int(changed.sum()), float(np.mean(np.abs(shift[changed])))))
        theta = identify(values, theta)
    a = values - predict(theta)
    _, flagged = nested_factor(a, b)
    _log.info("nested_done", rounds=len(rounds), reason=reason, corrected=sum(r.n_corrected for r in rounds))
    return NestedResult(theta, values, a, flagged, tuple(rounds), reason)


def prediction_std(jac: NDArray[np.float64], cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Standard uncertainty of predictions with Jacobian ``jac`` (m, p) and covariance: sqrt(diag(J C Jᵀ))."""
    j = np.asarray(jac, dtype=float)
    return np.asarray(np.sqrt(np.einsum("mp,pq,mq->m", j, cov, j)))
