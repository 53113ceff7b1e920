"""Seed 000's Table 2: statistics of the positioning error on check rows.

The positioning error of a row is ``e = measured − predicted`` (mm, measurement frame; seed 000:
ΔP = P_actual − P_theoretical, the theoretical position being the model's prediction). Per axis x,
y, z the table gives the *signed* components' mean and standard deviation and the largest absolute
component: seed 000 reports that after compensation "the error components in x, y and z are within
±0.2 mm" and "the mean value of error components in the three directions is close to zero", which
only makes sense for signed components. The 3-D (absolute positioning) error is ``|e|`` (seed 000
eq. 27) with its mean, standard deviation and maximum. Standard deviations are sample ones (n − 1).

Seed 000's own figures (KUKA KR210, 104 target points, absolute error): before compensation
max 0.76 / mean 0.42 mm; kinematic calibration max 0.42 / mean 0.24 mm; Chebyshev model with the
closed joint loop max 0.19 mm, every axis within ±0.2 mm.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["SEED000_TABLE2_MM", "error_statistics", "format_table2"]

SEED000_TABLE2_MM: dict[str, dict[str, float]] = {
    "before compensation": {"max": 0.76, "mean": 0.42},
    "kinematic calibration": {"max": 0.42, "mean": 0.24},
    "Chebyshev + closed loop": {"max": 0.19},
}


def error_statistics(measured_mm: NDArray[np.float64], predicted_mm: NDArray[np.float64]) -> dict[str, Any]:
    """Table 2 statistics of ``measured − predicted`` (both (n, 3), mm)."""
    e = np.asarray(measured_mm, dtype=float) - np.asarray(predicted_mm, dtype=float)
    if e.ndim != 2 or e.shape[1] != 3 or e.shape[0] == 0:
        raise ValueError(f"need (n, 3) positions with n >= 1, got {e.shape}")
    n = e.shape[0]
    ddof = 1 if n > 1 else 0
    d = np.linalg.norm(e, axis=1)
    out: dict[str, Any] = {"n": n}
    for k, axis in enumerate("xyz"):
        out[axis] = {
            "mean": float(e[:, k].mean()),
            "std": float(e[:, k].std(ddof=ddof)),
            "max_abs": float(np.abs(e[:, k]).max()),
        }
    out["3d"] = {
        "mean": float(d.mean()),
        "std": float(d.std(ddof=ddof)),
        "max": float(d.max()),
        "rms": float(np.sqrt(np.mean(d**2))),
    }
    return out


def format_table2(
    rows: Mapping[str, Mapping[str, Any]], timing: Mapping[str, Mapping[str, float]] | None = None
) -> str:
    """A text table: one line per model, per-axis mean/std/max|·| and 3-D mean/std/max (mm); with
    ``timing`` (per model ``fit_s`` and ``predict_s``) also the 3-D RMS and the two times."""
    w = max([12, *(len(name) for name in rows)])
    head = (
        f"{'model':<{w}} {'n':>4} | "
        + " | ".join(f"{ax + ' mean':>7} {'std':>6} {'max|.|':>6}" for ax in "xyz")
        + f" | {'3D mean':>7} {'std':>6} {'max':>6}"
        + (f" | {'3D rms':>6} {'fit s':>7} {'pred ms':>8}" if timing is not None else "")
    )
    lines = [head, "-" * len(head)]
    for name, st in rows.items():
        cells = " | ".join(
            f"{st[ax]['mean']:>7.3f} {st[ax]['std']:>6.3f} {st[ax]['max_abs']:>6.3f}" for ax in "xyz"
        )
        d = st["3d"]
        line = f"{name:<{w}} {st['n']:>4} | {cells} | {d['mean']:>7.3f} {d['std']:>6.3f} {d['max']:>6.3f}"
        if timing is not None:
            t = timing[name]
            line += f" | {d['rms']:>6.3f} {t['fit_s']:>7.2f} {1e3 * t['predict_s']:>8.2f}"
        lines.append(line)
    return "\n".join(lines)
