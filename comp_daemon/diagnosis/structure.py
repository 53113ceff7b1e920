"""Structure in the remainder that no effect of the ladder names: time, axes, load, temperature, direction.

After the ladder, the remainder (``measured − final twin``, mm) of every row is tested against each
variable a campaign offers: time (``t_s``, or ``pose_order``, the row order, when there is none),
the axis values ``a1``..``a6``, ``payload_kg``, ``temp_c`` and the approach directions
``dir1``..``dir6`` where present and not constant. The remainder is out of sample on every row:
check rows as they are, fit rows out of fold (the final model refitted without the row's fold, see
:meth:`~comp_daemon.diagnosis.stats.LinearProblem.oof_residuals`), so the test works without check
rows too and a model's own fit does not hide structure.

The regression on one variable is piecewise constant: the rows are cut into up to
:data:`N_BINS` quantile bins of the variable (one bin per value for a variable with few values, such
as a direction), and each of x, y, z is predicted by its bin mean. It is fitted out of fold
(k folds of pose groups); ``share_pct`` is the share of the remainder's variance (about its
out-of-fold mean) that the bin means explain on held-out rows — a step, a trend or a bump in the
variable all show. Significance is a permutation test: the variable is permuted
(:data:`N_PERMUTATIONS_FIRST`, then up to :data:`N_PERMUTATIONS` when the first round leaves it
possible), and the p-value is the share of permutations that explain at least as much; the
variables are significant at Holm's step-down correction of :data:`ALPHA` over all variables tested.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.diagnosis.stats import make_folds

__all__ = [
    "ALPHA",
    "N_BINS",
    "N_PERMUTATIONS",
    "N_PERMUTATIONS_FIRST",
    "TIME_VARIABLES",
    "StructureResult",
    "describe_structure",
    "residual_structure",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: family-wise significance level over the variables tested (Holm)
ALPHA = 0.01
#: at most this many quantile bins per variable
N_BINS = 8
#: permutations of the first round, and in all when the first round leaves significance possible
N_PERMUTATIONS_FIRST = 199
N_PERMUTATIONS = 2999
#: the names of the time variables
TIME_VARIABLES = ("t_s", "pose_order")
#: permutations whose out-of-fold shares are computed together
_BLOCK = 512


@dataclass(frozen=True)
class StructureResult:
    """One variable tested against the remainder."""

    against: str
    share_pct: float
    p_value: float
    significant: bool
    permutations: int

    def to_json(self) -> dict[str, Any]:
        return {
            "against": self.against,
            "share_pct": round(self.share_pct, 2),
            "significant": self.significant,
            "p_value": float(f"{self.p_value:.3g}"),
        }


def _bins(values: FloatArray) -> IntArray:
    """Bin index of each row: one bin per value with few values, else quantile bins."""
    uniq = np.unique(values)
    if len(uniq) <= N_BINS:
        return np.searchsorted(uniq, values).astype(np.int64)
    edges = np.quantile(values, np.linspace(0.0, 1.0, N_BINS + 1)[1:-1])
    return np.searchsorted(np.unique(edges), values, side="right").astype(np.int64)


def _oof_shares(resid: FloatArray, bins: IntArray, fold: IntArray) -> FloatArray:
    """Out-of-fold share of variance explained by the bin means, for each row of ``bins`` (P, n).

    Every permutation at once: one pass per quantity (count, x, y, z) sums the rows per
    (permutation, fold, bin); a fold's training means are the totals less the fold's own sums, and
    its held-out squared error is ``Σ r² − Σ_k (2·m_k·S_k − m_k²·N_k)`` over the bins k of its rows
    (``S_k``, ``N_k`` the fold's sum and count in bin k, ``m_k`` the training mean there). Done in
    blocks of :data:`_BLOCK` permutations to bound the memory.
    """
    n_perm = bins.shape[0]
    n_bins = int(bins.max()) + 1
    n_folds = int(fold.max()) + 1
    held = [fold == f for f in range(n_folds)]
    # per fold: the training mean (the prediction in a bin without training rows), Σ r² held out
    mean_train = np.array([resid[~rows].mean(axis=0) for rows in held])  # (F, 3)
    r2_held = sum(float(np.sum(resid[rows] ** 2)) for rows in held)
    sst = sum(float(np.sum((resid[rows] - mean_train[f]) ** 2)) for f, rows in enumerate(held))
    if sst <= 0.0:
        return np.zeros(n_perm)
    out = np.empty(n_perm)
    cells = n_folds * n_bins
    for start in range(0, n_perm, _BLOCK):
        block = bins[start : start + _BLOCK]
        p = block.shape[0]
        key = (block + (fold * n_bins)[None, :] + (np.arange(p) * cells)[:, None]).ravel()
        count = np.bincount(key, minlength=p * cells).reshape(p, n_folds, n_bins).astype(float)
        count_train = count.sum(axis=1, keepdims=True) - count
        gain = np.zeros(p)
        for c in range(3):
            sums = np.bincount(key, weights=np.tile(resid[:, c], p), minlength=p * cells)
            sums = sums.reshape(p, n_folds, n_bins)
            sums_train = sums.sum(axis=1, keepdims=True) - sums
            fallback = np.broadcast_to(mean_train[None, :, c, None], sums.shape)
            means = np.divide(sums_train, count_train, out=fallback.copy(), where=count_train > 0)
            gain += np.sum(means * (2.0 * sums - means * count), axis=(1, 2))
        out[start : start + p] = 1.0 - (r2_held - gain) / sst
    return out


def _test(
    resid: FloatArray, values: FloatArray, fold: IntArray, rng: np.random.Generator, threshold: float
) -> tuple[float, float, int]:
    """Observed share, permutation p-value and the number of permutations used."""
    bins = _bins(values)
    observed = float(_oof_shares(resid, bins[None, :], fold)[0])
    n = len(values)
    exceed = 0
    done = 0
    for total in (N_PERMUTATIONS_FIRST, N_PERMUTATIONS):
        k = total - done
        perms = np.argsort(rng.random((k, n)), axis=1)
        shares = _oof_shares(resid, bins[perms], fold)
        exceed += int(np.sum(shares >= observed))
        done = total
        if (exceed + 1) / (N_PERMUTATIONS + 1) >= threshold:
            break  # cannot become significant even after every permutation
    return observed, (exceed + 1) / (done + 1), done


def _variables(columns: dict[str, FloatArray | None]) -> dict[str, FloatArray]:
    """The variables present and not constant, in the order given."""
    out: dict[str, FloatArray] = {}
    for name, values in columns.items():
        if values is None:
            continue
        v = np.asarray(values, dtype=float)
        if np.all(np.isfinite(v)) and np.ptp(v) > 0.0:
            out[name] = v
    return out


def residual_structure(
    resid_mm: FloatArray,
    columns: dict[str, FloatArray | None],
    pose_group: IntArray,
    *,
    folds: int,
    seed: int,
) -> list[StructureResult]:
    """Test the remainder ``resid_mm`` (n, 3) against every variable of ``columns`` (name -> (n,)).

    Columns that are None or constant are left out. Folds are of pose groups (repeats together).
    """
    variables = _variables(columns)
    if not variables or len(resid_mm) < 2 * folds:
        return []
    fold = make_folds(pose_group, folds, seed)
    rng = np.random.default_rng(seed)
    m = len(variables)
    raw = {name: _test(resid_mm, v, fold, rng, ALPHA / m) for name, v in variables.items()}
    # Holm: the k-th smallest p-value is compared with ALPHA / (m − k); stop at the first failure
    order = sorted(raw, key=lambda name: raw[name][1])
    significant: set[str] = set()
    for k, name in enumerate(order):
        if raw[name][1] >= ALPHA / (m - k):
            break
        significant.add(name)
    return [
        StructureResult(
            against=name,
            share_pct=100.0 * max(share, 0.0),
            p_value=p,
            significant=name in significant,
            permutations=n_perm,
        )
        for name, (share, p, n_perm) in raw.items()
    ]


def _what(name: str) -> str:
    if name in TIME_VARIABLES:
        return "time" if name == "t_s" else "the order of the measurements"
    if name.startswith("a") and name[1:].isdigit():
        return f"the axis value A{name[1:]}"
    if name.startswith("dir"):
        return f"the approach direction of A{name[3:]}"
    return {"payload_kg": "the payload", "temp_c": "the temperature"}.get(name, name)


def describe_structure(results: list[StructureResult]) -> str:
    """The findings in words (empty when nothing was tested)."""
    if not results:
        return ""
    found = sorted((r for r in results if r.significant), key=lambda r: -r.share_pct)
    if not found:
        return (
            "The remainder shows no structure against "
            + ", ".join(r.against for r in results)
            + " (each tested out of fold against permutations)."
        )
    lead = found[0]
    words = (
        f"The remainder follows {_what(lead.against)} "
        f"({lead.against}: {lead.share_pct:.0f} % of it out of fold"
    )
    if len(found) > 1:
        words += "; also " + ", ".join(f"{r.against} {r.share_pct:.0f} %" for r in found[1:4])
    words += ")"
    if lead.against in TIME_VARIABLES:
        words += ": a change over time (a drift or a step) that no effect of the ladder names."
    else:
        words += f": structure in {_what(lead.against)} that no effect of the ladder names."
    return words
