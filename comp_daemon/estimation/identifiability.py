"""Identifiability of parameters from an identification Jacobian (seed 003, §1.3).

Seed 003 finds that the coefficient matrix of a position-based calibration is degenerate in two
ways: some columns are all zero (the parameter does not move the measured point), and some columns
are linearly dependent (only one of a dependent group can be identified). The first are removed,
of the second only one is kept.

Method. The Jacobian (n, 3, p) is stacked to (3n, p) and every column scaled to unit norm, so that
parameters in mm and in rad compare. A column whose norm is below ``zero_rtol`` times the largest
column norm is *zero*. The others are offered one by one in a priority order (the caller's, or
:func:`mdh_priority` for the kinematic parameters) and kept when the part of the scaled column that
the kept columns cannot express (the Gram–Schmidt residual) is larger than ``rtol``; otherwise the
column is *dependent*, and the least-squares combination of kept columns that reproduces it is
reported (the names it depends on, largest contribution first). The kept set is a basis of the
column space, chosen in priority order. The numerical rank (relative tolerance ``rank_rtol``) is
checked independently by QR with column pivoting and by the SVD of the scaled matrix; both are
reported. With ``rtol`` far above rounding (a data-driven model, where nearly dependent columns
would let coefficients explode) fewer columns than the rank are kept: a kept column then has at least
``rtol`` of its scaled norm outside the span of the columns kept before it.

:func:`mdh_priority` orders the 39 kinematic parameters (:data:`PARAM_NAMES`): the base frame first,
then the tool (frames of the measurement set-up, kept whenever they are observable), then per joint
``theta, d, a, alpha`` — with ``beta`` in place of ``d`` for a joint whose axis is parallel to the
previous one (Hayati's MDH, seed 003 eq. 2) — and the remaining ``beta`` / ``d`` last.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from comp_daemon.kinematics.params import JOINT_PARAM_KINDS, PARAM_NAMES, KinematicParams

__all__ = [
    "IdentifiabilityReport",
    "RemovedParameter",
    "analyze_identifiability",
    "mdh_priority",
    "offer_order",
    "parallel_joints",
    "select_columns",
]


@dataclass(frozen=True, slots=True)
class RemovedParameter:
    """A parameter the data cannot identify: ``zero`` column, or ``dependent`` on kept ones.

    For a dependent one, ``column ≈ Σ coefficients[k] · column(depends_on[k])`` (unscaled columns;
    only the terms that contribute at least ``1e-6`` of the column's norm are listed).
    """

    name: str
    reason: Literal["zero", "dependent"]
    depends_on: tuple[str, ...]
    coefficients: tuple[float, ...]
    residual: float  # scaled Gram–Schmidt residual (0 … 1); 0 for a zero column

    def describe(self) -> str:
        if self.reason == "zero":
            return f"{self.name}: zero column (does not move the measured point)"
        terms = " ".join(
            f"{'+' if c >= 0 else '-'} {abs(c):.6g}·{n}"
            for n, c in zip(self.depends_on, self.coefficients, strict=True)
        )
        return f"{self.name}: dependent, = {terms.lstrip('+ ')} (residual {self.residual:.1e})"


@dataclass(frozen=True, slots=True)
class IdentifiabilityReport:
    names: tuple[str, ...]  # all column names of the Jacobian
    candidates: tuple[str, ...]  # the columns analysed, in priority order
    identifiable: tuple[str, ...]  # kept, in column order
    identifiable_index: NDArray[np.intp]  # their column indices
    removed: tuple[RemovedParameter, ...]
    rank_qr: int
    rank_svd: int
    singular_values: NDArray[np.float64]  # of the scaled candidate columns
    condition_number: float  # of the scaled identifiable columns
    smallest_kept_residual: float  # the weakest identifiable column's Gram–Schmidt residual (vs rtol)

    @property
    def n_identifiable(self) -> int:
        return len(self.identifiable)

    def removed_names(self, reason: str | None = None) -> tuple[str, ...]:
        return tuple(r.name for r in self.removed if reason is None or r.reason == reason)

    def summary(self) -> str:
        lines = [
            f"{self.n_identifiable} of {len(self.candidates)} parameters identifiable "
            f"(rank by pivoted QR {self.rank_qr}, by SVD {self.rank_svd}; "
            f"condition number of the scaled columns {self.condition_number:.3g}; "
            f"weakest kept residual {self.smallest_kept_residual:.2g})",
            "identifiable: " + ", ".join(self.identifiable),
        ]
        lines += ["removed " + r.describe() for r in self.removed]
        return "\n".join(lines)


def parallel_joints(params: KinematicParams, tol_rad: float = 1e-6) -> tuple[bool, ...]:
    """For link i = 1..6: is the next joint's axis z_i parallel to joint i's axis z_{i-1}?

    (alpha_i ≈ 0 or ±180°.) Link 6 ends in the flange, not in a joint axis: always False.
    """
    return tuple(bool(i < 5 and abs(np.sin(a)) < tol_rad) for i, a in enumerate(params.alpha_rad))


def mdh_priority(
    params: KinematicParams, names: Sequence[str] = PARAM_NAMES, extra: Sequence[str] = ()
) -> tuple[str, ...]:
    """The order in which :func:`analyze_identifiability` offers the 39 kinematic parameters.

    ``extra`` names (e.g. non-geometric effects) are offered after the MDH parameters and before
    the left-over ``beta`` / ``d`` of each joint.
    """
    parallel = parallel_joints(params)
    first: list[str] = [n for n in names if n.startswith("base_")] + [
        n for n in names if n.startswith("tool_")
    ]
    last: list[str] = []
    for j in range(1, 7):
        primary = ("theta", "beta", "a", "alpha") if parallel[j - 1] else ("theta", "d", "a", "alpha")
        first += [f"{k}{j}" for k in primary]
        last += [f"{k}{j}" for k in JOINT_PARAM_KINDS if k not in primary]
    order = [n for n in first if n in names] + list(extra) + [n for n in last if n in names]
    order += [n for n in names if n not in order]
    return tuple(order)


def analyze_identifiability(
    jac: NDArray[np.float64],
    names: Sequence[str],
    *,
    candidates: Sequence[str] | None = None,
    priority: Sequence[str] | None = None,
    rtol: float | Mapping[str, float] = 1e-8,
    zero_rtol: float = 1e-10,
    rank_rtol: float = 1e-8,
    check_rank: bool = True,
    check_condition: bool = True,
    describe_dependent: bool = True,
) -> IdentifiabilityReport:
    """Zero and dependent columns of ``jac`` ((n, 3, p) or (m, p)), by name (module docstring).

    ``candidates``: the names to analyse (default all); the others are not part of the problem.
    ``priority``: the order in which candidates are offered (default: ``candidates`` order);
    names in ``priority`` that are not candidates are skipped. ``rtol``: one tolerance, or one per
    candidate name. ``check_rank=False`` skips the independent rank checks (reported as -1),
    ``check_condition=False`` the condition number (reported as NaN): neither changes which
    parameters are identifiable, and a fit that needs only those (a cross-validation fold) saves
    two thirds of the analysis. ``describe_dependent=False`` reports the dependent columns without
    the combination of kept columns that reproduces them (``depends_on`` and ``coefficients``
    empty), for the same fits.
    """
    a = np.asarray(jac, dtype=float)
    if a.ndim == 3:
        a = a.reshape(-1, a.shape[-1])
    if a.ndim != 2:
        raise ValueError(f"Jacobian must be (n, 3, p) or (m, p), got shape {np.shape(jac)}")
    names = tuple(names)
    if len(names) != a.shape[1]:
        raise ValueError(f"{len(names)} names for a Jacobian with {a.shape[1]} columns")
    if len(set(names)) != len(names):
        raise ValueError("parameter names must be unique")
    index = {n: i for i, n in enumerate(names)}
    order = offer_order(index, candidates, priority)
    cols = np.array([index[n] for n in order], dtype=np.intp)
    tol = _tolerances(rtol, order)
    sub = a[:, cols]
    norms = np.linalg.norm(sub, axis=0)
    max_norm = float(norms.max(initial=0.0))
    is_zero = norms <= zero_rtol * max_norm if max_norm > 0 else np.ones(len(order), dtype=bool)
    scaled = sub / np.where(is_zero, 1.0, norms)

    kept, kept_res, status = select_columns(scaled, is_zero, tol)
    removed = _removed(order, scaled, norms, kept, status, describe_dependent)
    rank_qr, rank_svd, sv = _ranks(scaled[:, ~is_zero], rank_rtol) if check_rank else (-1, -1, np.zeros(0))
    if kept and check_condition:
        sv_kept = np.linalg.svd(scaled[:, kept], compute_uv=False)
        cond = float(sv_kept[0] / sv_kept[-1]) if sv_kept[-1] > 0 else float("inf")
    else:
        cond = float("nan")
    kept_index = np.sort(cols[kept])
    return IdentifiabilityReport(
        names=names,
        candidates=tuple(order),
        identifiable=tuple(names[i] for i in kept_index),
        identifiable_index=kept_index,
        removed=tuple(removed),
        rank_qr=rank_qr,
        rank_svd=rank_svd,
        singular_values=sv,
        condition_number=cond,
        smallest_kept_residual=min(kept_res, default=float("nan")),
    )


def offer_order(
    index: Mapping[str, int], candidates: Sequence[str] | None, priority: Sequence[str] | None
) -> list[str]:
    """The candidates (default every name of ``index``) in the order they are offered: those named in
    ``priority`` first, in its order, then the rest in candidate order; a name neither column of
    the Jacobian is a ``ValueError`` naming it."""
    cand = tuple(index if candidates is None else candidates)
    unknown = [n for n in cand if n not in index]
    if unknown:
        raise ValueError(f"unknown parameter name(s): {', '.join(unknown)}")
    if priority is None:
        return list(cand)
    missing = [n for n in priority if n not in index]
    if missing:
        raise ValueError(f"unknown parameter name(s) in priority: {', '.join(missing)}")
    cand_set = set(cand)
    order = [n for n in priority if n in cand_set]
    order += [n for n in cand if n not in set(order)]
    return order


def _tolerances(rtol: float | Mapping[str, float], order: Sequence[str]) -> NDArray[np.float64]:
    """The Gram–Schmidt tolerance of every offered column: one for all, or the caller's per name."""
    if not isinstance(rtol, Mapping):
        return np.full(len(order), float(rtol))
    missing_tol = [n for n in order if n not in rtol]
    if missing_tol:
        raise ValueError(f"no tolerance for: {', '.join(missing_tol)}")
    return np.array([float(rtol[n]) for n in order])


def select_columns(
    scaled: NDArray[np.float64], is_zero: NDArray[np.bool_], tol: NDArray[np.float64]
) -> tuple[list[int], list[float], dict[int, tuple[str, float]]]:
    """The basis of the column space in offer order (module docstring): the unit-norm columns
    ``scaled`` (m, q) are offered one by one and kept when the part the kept ones cannot express
    is longer than ``tol``. Returns the kept positions, their Gram–Schmidt residuals, and for every
    other position ``("zero", 0.0)`` or ``("dependent", residual)``."""
    rows_basis = np.empty((scaled.shape[1], scaled.shape[0]))  # the orthonormal basis, one vector a row
    kept: list[int] = []
    kept_res: list[float] = []
    status: dict[int, tuple[str, float]] = {}
    for pos in range(scaled.shape[1]):
        if is_zero[pos]:
            status[pos] = ("zero", 0.0)
            continue
        basis = rows_basis[: len(kept)]
        c = scaled[:, pos]
        r = c - (basis @ c) @ basis
        r = r - (basis @ r) @ basis  # re-orthogonalise once (classical Gram–Schmidt twice)
        res = float(np.linalg.norm(r))
        if res > tol[pos]:
            rows_basis[len(kept)] = r / res
            kept.append(pos)
            kept_res.append(res)
        else:
            status[pos] = ("dependent", res)
    return kept, kept_res, status


def _removed(
    order: Sequence[str],
    scaled: NDArray[np.float64],
    norms: NDArray[np.float64],
    kept: list[int],
    status: Mapping[int, tuple[str, float]],
    describe: bool,
) -> list[RemovedParameter]:
    """The removed columns in offer order; a dependent one with the least-squares combination of the
    kept columns that reproduces it (unscaled coefficients, largest contribution first) when
    ``describe`` and anything was kept."""
    removed: list[RemovedParameter] = []
    dependent = [pos for pos in sorted(status) if status[pos][0] == "dependent"]
    explain = describe and bool(kept)
    if dependent and explain:
        # all dependent columns at once, in the kept columns' scaled basis
        coef_all, *_ = np.linalg.lstsq(scaled[:, kept], scaled[:, dependent], rcond=None)
    for pos in sorted(status):
        reason, res = status[pos]
        if reason == "zero":
            removed.append(RemovedParameter(order[pos], "zero", (), (), 0.0))
            continue
        scaled_coef = coef_all[:, dependent.index(pos)] if explain else np.zeros(0)
        coef = scaled_coef * norms[pos] / norms[kept] if explain else scaled_coef
        contrib = np.abs(scaled_coef)
        significant = np.flatnonzero(contrib >= 1e-6)
        significant = significant[np.argsort(-contrib[significant], kind="stable")]
        removed.append(
            RemovedParameter(
                order[pos],
                "dependent",
                tuple(order[kept[k]] for k in significant),
                tuple(float(coef[k]) for k in significant),
                res,
            )
        )
    return removed


def _ranks(nonzero: NDArray[np.float64], rank_rtol: float) -> tuple[int, int, NDArray[np.float64]]:
    """The independent rank checks of the non-zero scaled columns: by pivoted QR, by SVD (relative
    tolerance ``rank_rtol``), and the singular values."""
    if not nonzero.shape[1]:
        return 0, 0, np.zeros(0)
    _, r_qr, _ = scipy.linalg.qr(nonzero, mode="economic", pivoting=True)
    diag = np.abs(np.diag(r_qr))
    rank_qr = int(np.sum(diag > rank_rtol * diag[0])) if diag[0] > 0 else 0
    sv = np.asarray(np.linalg.svd(nonzero, compute_uv=False), dtype=np.float64)
    rank_svd = int(np.sum(sv > rank_rtol * sv[0])) if sv[0] > 0 else 0
    return rank_qr, rank_svd, sv
