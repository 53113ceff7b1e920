"""What both trial reports (text and HTML) show, picked out of a trial result."""

from __future__ import annotations

from typing import Any

import numpy as np

from comp_daemon.trial.result import TrialResult
from comp_daemon.trial.verdict import SEED000, TABLE_ROWS

__all__ = ["COMPARISONS", "grating_scale", "iso_retried", "seed_figure", "table_rows"]

COMPARISONS = (
    ("open", "open-loop data"),
    ("open-gratings", "open-loop data with A1–A3 read from the gratings"),
    ("closed", "closed-loop data"),
)


def table_rows(result: TrialResult) -> list[str]:
    """Every method run with a measured target point, in the order of Table 2: the rows of the
    tables and the series of every figure (seed 000's three and the trial's further ones)."""
    return [k for k in TABLE_ROWS if k in result.runs and result.runs[k].ok.any()]


def grating_scale(m: dict[str, Any]) -> float:
    """Fitted slope over the nominal one of a grating map (JointGratingMap.scale)."""
    return float(m["slope_deg_per_count"]) / float(np.degrees(m["resolution_nm"] * 1e-6 / m["radius_mm"]))


def iso_retried(result: TrialResult) -> list[str]:
    return list(result.iso.get("runs", {}).get("with", {}).get("retried", []))


def seed_figure(key: str, field: str) -> str:
    v = SEED000.get(key, {}).get(field)
    return "" if v is None else f"{v:.2f}"
