"""What a campaign's rows cover: the axes that move on the rows a model is fitted on.

A model is determined only where the campaign went; an axis that never moves on the fit rows
leaves every model's dependence on it unknown (the fit holds at that one value and extrapolates
elsewhere), which :func:`still_axes_note` says in one sentence.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.table import Dataset

__all__ = ["STILL_AXIS_DEG", "still_axes_note"]

#: an axis whose values on the fit rows span less than this (deg) did not move in the campaign
STILL_AXIS_DEG = 0.01


def still_axes_note(dataset: Dataset, rows: NDArray[np.intp]) -> str | None:
    """A sentence naming the axes that do not move on ``rows`` (a model is then determined only at
    their values there), or None when every axis moves."""
    assert dataset.a_deg is not None
    span = np.ptp(dataset.a_deg[rows], axis=0)
    still = [f"A{k + 1}" for k in range(6) if span[k] < STILL_AXIS_DEG]
    if not still:
        return None
    held = ", ".join(
        f"A{k + 1} {dataset.a_deg[rows][0, k]:.3f}°" for k in range(6) if span[k] < STILL_AXIS_DEG
    )
    return (
        f"{', '.join(still)} {'does' if len(still) == 1 else 'do'} not move on the fit rows ({held}): "
        "a model is determined only at "
        "these values; elsewhere it extrapolates"
    )
