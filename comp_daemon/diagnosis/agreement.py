"""Whether the fit rows and the check rows tell the same story, and what differs when they do not.

The ladder chooses its effects on the fit rows (their error out of fold, ``cv_rms_mm``) and reports
them on the check rows (``check_rms_mm``). When the two disagree, the check rows are not a sample of
the same campaign as the fit rows, and no effect the ladder names can be trusted. Two signs:

- along the ladder, from the geometric step to the last significant step, the fit rows' error out
  of fold falls while the check rows' error rises by more than :data:`RISE` (relative);
- at the geometric step already, the check rows' error exceeds the fit rows' out-of-fold error by
  more than :data:`GAP_FACTOR` times: the geometry fitted on one set does not hold on the other.

What differs between the rows is then looked for, each with its figure:

- **frame or station**: a rigid motion fitted to the check rows alone (the final twin's TCPs onto
  the measured ones, Kabsch) removes most of their error (more than :data:`FRAME_SHARE`): the check
  rows were measured in another frame (the tracker moved, another station). A ``station`` column
  whose values differ between fit and check rows is named too;
- **axis ranges**: check rows with an axis outside the fit rows' range (more than
  :data:`RANGE_MARGIN_DEG`): the twin extrapolates there;
- **time**: the check rows' clock lies outside the fit rows' (less than half of the check rows
  within the fit rows' clock range).

The verdict: :class:`Agreement`; when ``agree`` is False the summary gives no effect advice.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.table import Dataset
from comp_daemon.estimation.registration import frame_changes, rigid_registration
from comp_daemon.models.rows import MeasuredRows

__all__ = ["Agreement", "fit_check_agreement"]

FloatArray = NDArray[np.float64]


def _r(value: float) -> float:
    return float(f"{value:.6g}") if np.isfinite(value) and value != 0.0 else float(value)


#: the check error must rise by more than this share along the ladder to count as rising
RISE = 0.05
#: the geometric step's check error above this multiple of its fit rows' CV error is a disagreement
GAP_FACTOR = 2.0
#: a rigid motion of the check rows that removes more than this share of their squared error
FRAME_SHARE = 0.5
#: a check row's axis beyond the fit rows' range by more than this (deg) is outside it
RANGE_MARGIN_DEG = 0.5


@dataclass(frozen=True)
class Agreement:
    """The fit and check rows' errors along the ladder, and what differs when they disagree."""

    agree: bool
    reason: str  # why they are said to disagree ("" when they agree)
    check_rms_mm: list[float]  # geometric step, then each significant step
    cv_rms_mm: list[float]
    differences: list[str] = field(default_factory=list)  # what differs, in words
    details: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        if self.agree:
            return ""
        found = (
            "; ".join(self.differences)
            if self.differences
            else ("neither a frame, the axis ranges nor the time tells them apart: check the split")
        )
        return (
            f"The fit and check rows disagree: {self.reason}. What differs between them: {found}. "
            "No effect advice is given until that is resolved (measure the check rows as the fit rows "
            "were measured, or split the campaign so both sides cover the same frame, ranges and time)."
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "agree": self.agree,
            "reason": self.reason,
            "check_rms_mm": [_r(v) for v in self.check_rms_mm],
            "cv_rms_mm": [_r(v) for v in self.cv_rms_mm],
            "differences": self.differences,
            **self.details,
        }


def fit_check_agreement(
    check_rms_mm: Sequence[float],
    cv_rms_mm: Sequence[float | None],
    obs: MeasuredRows,
    fit_rows: NDArray[np.int64],
    check_rows: NDArray[np.int64],
    predicted_check_mm: FloatArray,
    dataset: Dataset,
) -> Agreement:
    """The :class:`Agreement` of a ladder (module docstring): ``check_rms_mm`` and ``cv_rms_mm`` of
    the geometric step and of each significant step after it; ``predicted_check_mm`` (n_check, 3)
    the final twin's TCP on the check rows."""
    check = [float(v) for v in check_rms_mm]
    cv = [float("nan") if v is None else float(v) for v in cv_rms_mm]
    reason = ""
    if len(check) > 1 and check[-1] > (1.0 + RISE) * check[0] and cv[-1] < cv[0]:
        reason = (
            f"along the ladder the fit rows' error out of fold falls ({cv[0]:.4f} → {cv[-1]:.4f} mm) "
            f"while the check rows' error rises ({check[0]:.4f} → {check[-1]:.4f} mm)"
        )
    elif np.isfinite(cv[0]) and check[0] > GAP_FACTOR * cv[0]:
        reason = (
            f"after the geometric step the check rows' error ({check[0]:.4f} mm) is "
            f"{check[0] / cv[0]:.1f} times the fit rows' error out of fold ({cv[0]:.4f} mm)"
        )
    if not reason:
        return Agreement(True, "", check, cv)
    differences, details = _differences(obs, fit_rows, check_rows, predicted_check_mm, dataset)
    return Agreement(False, reason, check, cv, differences, details)


def _differences(
    obs: MeasuredRows,
    fit_rows: NDArray[np.int64],
    check_rows: NDArray[np.int64],
    predicted_check_mm: FloatArray,
    dataset: Dataset,
) -> tuple[list[str], dict[str, Any]]:
    words: list[str] = []
    details: dict[str, Any] = {}
    # frame: a rigid motion of the check rows alone
    measured = obs.xyz_mm[check_rows]
    before = float(np.sum((measured - predicted_check_mm) ** 2))
    if len(check_rows) >= 4 and before > 0:
        t = rigid_registration(predicted_check_mm, measured)
        moved = predicted_check_mm @ t[:3, :3].T + t[:3, 3]
        after = float(np.sum((measured - moved) ** 2))
        share = 1.0 - after / before
        angle = float(np.degrees(np.arccos(np.clip((np.trace(t[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
        shift = float(np.linalg.norm(t[:3, 3]))
        details["check_frame"] = {
            "share_pct": round(100 * share, 1),
            "angle_deg": _r(angle),
            "shift_mm": _r(shift),
        }
        if share > FRAME_SHARE:
            words.append(
                f"frame: a rigid motion of the check rows alone ({angle:.3f}° and {shift:.3f} mm at the "
                f"origin) removes {100 * share:.0f} % of their squared error — they look measured in "
                "another frame (the tracker moved, or another station)"
            )
    station = dataset.station
    if station is not None:
        fit_st = sorted({station[int(i)] for i in fit_rows})
        check_st = sorted({station[int(i)] for i in check_rows})
        if fit_st != check_st:
            details["stations"] = {"fit": fit_st, "check": check_st}
            words.append(f"station: fit rows from {', '.join(fit_st)}, check rows from {', '.join(check_st)}")
        judged = frame_changes([station[int(i)] for i in check_rows], predicted_check_mm, measured)
        if judged:
            details["check_by_station"] = {j.station: j.to_json() for j in judged}
        words += [j.describe() for j in judged if j.changed]
    # axis ranges
    lo, hi = obs.a_deg[fit_rows].min(axis=0), obs.a_deg[fit_rows].max(axis=0)
    a_check = obs.a_deg[check_rows]
    outside = (a_check < lo - RANGE_MARGIN_DEG) | (a_check > hi + RANGE_MARGIN_DEG)
    per_axis = outside.sum(axis=0)
    details["check_rows_outside_fit_ranges"] = {f"a{k + 1}": int(c) for k, c in enumerate(per_axis) if c}
    if per_axis.any():
        axes = ", ".join(f"A{k + 1} {int(c)}" for k, c in enumerate(per_axis) if c)
        words.append(
            f"axis ranges: {int(outside.any(axis=1).sum())} of {len(check_rows)} check rows lie outside "
            f"the fit rows' range ({axes}): the twin extrapolates there"
        )
    # time
    if obs.clock is not None and len(fit_rows):
        c_fit, c_check = obs.clock[fit_rows], obs.clock[check_rows]
        within = float(np.mean((c_check >= c_fit.min()) & (c_check <= c_fit.max())))
        details["check_rows_within_fit_clock_pct"] = round(100 * within, 1)
        if within < 0.5:
            unit = "h" if obs.clock_name == "t_s" else "rows"
            words.append(
                f"time: {100 * (1 - within):.0f} % of the check rows lie outside the fit rows' "
                f"{obs.clock_name} span ({c_fit.min():.4g}–{c_fit.max():.4g} {unit}; check rows "
                f"{c_check.min():.4g}–{c_check.max():.4g})"
            )
    return words, details
