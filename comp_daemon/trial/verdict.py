"""What a trial says: seed 000's figures beside the trial's, the ordering of the methods, the claim.

Seed 000 (Table 2 and its text, 104 target points, 3-D absolute error, mm): before compensation
max 0.76 / mean 0.42; kinematic calibration max 0.42 / mean 0.24; Chebyshev model + joint closed
loop max 0.19 with every axis component within ±0.2 (−75 % of the maximum against "before",
−55 % against kinematic calibration). The seed gives no other cell of Table 2 in its text.
"""

from __future__ import annotations

from typing import Any

from comp_daemon.trial.result import TrialResult

__all__ = ["SEED000", "TABLE_ROWS", "verdict"]

#: seed 000's figures per run key (3-D mean / max, per-axis bound), mm
SEED000: dict[str, dict[str, float]] = {
    "uncompensated": {"mean": 0.42, "max": 0.76},
    "kinematic": {"mean": 0.24, "max": 0.42},
    "chebyshev+feedback": {"max": 0.19, "axis_max_abs": 0.2},
}
#: run keys in the order of Table 2
TABLE_ROWS = (
    "uncompensated",
    "kinematic",
    "feedback",
    "kinematic+feedback",
    "chebyshev+feedback",
    "chebyshev-seed000+feedback",
)


def verdict(result: TrialResult) -> dict[str, Any]:
    """Ordering of the methods (3-D mean and max) and the trial's numbers beside seed 000's claim."""
    t2 = result.table2()
    out: dict[str, Any] = {}
    keys = ("uncompensated", "kinematic", "chebyshev+feedback")
    if all(k in t2 for k in keys):
        u, k, c = (t2[x]["3d"] for x in keys)
        out["ordering"] = {
            "mean": bool(c["mean"] < k["mean"] < u["mean"]),
            "max": bool(c["max"] < k["max"] < u["max"]),
            "closed_loop_beats_kinematic": bool(c["mean"] < k["mean"] and c["max"] < k["max"]),
            "kinematic_beats_uncompensated": bool(k["mean"] < u["mean"] and k["max"] < u["max"]),
        }
        axis_max = max(t2["chebyshev+feedback"][a]["max_abs"] for a in "xyz")
        out["claim"] = {
            "seed000": {"before_max": 0.76, "after_max": 0.19, "reduction": 0.75, "vs_kinematic": 0.55},
            "trial": {
                "before_max": u["max"],
                "after_max": c["max"],
                "reduction": 1.0 - c["max"] / u["max"],
                "vs_kinematic": 1.0 - c["max"] / k["max"],
                "axis_max_abs": axis_max,
                "before_mean": u["mean"],
                "after_mean": c["mean"],
            },
            "after_max_within_0_19": bool(c["max"] <= 0.19),
            "axes_within_0_2": bool(axis_max <= 0.2),
        }
    return out
