"""Approach directions from the pose order, for campaigns that record only axis values.

Backlash makes a joint stop on one flank or the other depending on the sign of its last motion
(the ``dir`` columns of docs/data-format.md). Most real campaigns do not record it, but the rows
are in the order the robot visited them, so each axis' last motion before row ``i`` is the last
non-zero change of that axis up to row ``i``. An axis that has not moved since the first row has
no known approach: its direction is taken as +1 and counted as assumed, so a caller can say so or
leave those rows out.

Where the ``t_s`` column exists the rows are put in time order first; otherwise file order is the
visiting order (as in every campaign written by ``comp-daemon sim sample``), an assumption
:data:`ROW_ORDER_ASSUMPTION` says wherever such directions are used. Every door takes them through
:func:`comp_daemon.preparation.campaign.prepare_directions`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["ROW_ORDER_ASSUMPTION", "DirectionInference", "infer_directions"]

STILL_DEG = 1e-6  # an axis change smaller than this is no motion

#: the assumption behind directions inferred from the file's row order, said wherever they are used
ROW_ORDER_ASSUMPTION = (
    "assumed: the file lists the poses in the order the robot visited them (no t_s column); "
    "if it does not, these directions are wrong and a backlash fitted on them means nothing "
    "(give dir1..dir6 or t_s to make them certain)"
)


@dataclass(frozen=True, slots=True)
class DirectionInference:
    """What :func:`infer_directions` derived, and how much of it is assumed."""

    dir: NDArray[np.int8]  # (n, 6) in {-1, +1}
    assumed: NDArray[np.bool_]  # (n, 6): no motion of that axis before the row; +1 assumed
    order: str  # "t_s" or "row order"

    @property
    def assumed_rows(self) -> int:
        """Rows where at least one axis' direction had to be assumed."""
        return int(self.assumed.any(axis=1).sum())

    def describe(self) -> str:
        """One sentence: how the directions were derived, the rows where an axis had not moved yet
        (unknown: a caller sets them to 0, no backlash offset), and, in row order, the assumption."""
        text = (
            "approach directions (dir1..dir6) inferred from the sign of each axis' last motion"
            f" in {self.order}"
        )
        per_axis = self.assumed.sum(axis=0)
        if per_axis.any():
            counts = ", ".join(f"A{k + 1} {int(c)}" for k, c in enumerate(per_axis) if c)
            text += f"; unknown (0) before an axis first moved, rows of {len(self.dir)}: {counts}"
        if self.order == "row order":
            text += "; " + ROW_ORDER_ASSUMPTION
        return text


def infer_directions(
    a_deg: NDArray[np.float64], t_s: NDArray[np.float64] | None = None
) -> DirectionInference:
    """Approach direction of each axis at each row, from the sign of its last motion.

    ``a_deg`` (n, 6) axis values in visiting order, or in any order when ``t_s`` (n,) gives the
    time of each row (ties keep file order).
    """
    a = np.asarray(a_deg, dtype=float)
    if a.ndim != 2 or a.shape[1] != 6:
        raise ValueError(f"axis values must be (n, 6), got {a.shape}")
    n = len(a)
    order = np.arange(n) if t_s is None else np.argsort(np.asarray(t_s, dtype=float), kind="stable")
    visited = a[order]
    step = np.diff(visited, axis=0, prepend=visited[:1])
    moved = np.abs(step) > STILL_DEG
    sign = np.where(moved, np.sign(step), 0.0)
    # carry the last non-zero sign forward: index of the last moving row up to each row
    idx = np.where(moved, np.arange(n)[:, None], -1)
    last = np.maximum.accumulate(idx, axis=0)
    known = last >= 0
    carried = np.where(known, sign[np.clip(last, 0, None), np.arange(6)], 1.0)
    out_dir = np.empty((n, 6), np.int8)
    out_assumed = np.empty((n, 6), bool)
    out_dir[order] = carried.astype(np.int8)
    out_assumed[order] = ~known
    return DirectionInference(
        dir=out_dir, assumed=out_assumed, order="t_s" if t_s is not None else "row order"
    )
