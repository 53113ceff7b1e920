"""Statistics of the trial: ISO 9283 multi-directional pose accuracy, Table 2, histograms.

ISO 9283 (7.2.3 pose repeatability, 7.2.4 multi-directional pose accuracy variation), for attained
positions ``(points, 3 directions, cycles, 3)`` in mm:

- barycentre of one direction ``x̄_d = mean over cycles``;
- ``vAP`` = the largest distance between the barycentres of the three directions;
- ``RP_d = l̄ + 3·S_l`` with ``l`` the distances of the attained positions of direction d to their
  barycentre (``S_l`` the sample standard deviation); the table shows the largest of the three.

Table 2 (seed 000) is :func:`comp_daemon.models.evaluation.error_statistics` of ``measured − wanted``:
signed per-axis mean/std, max |component|, and the 3-D error's mean/std/max (eq. 27).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["histogram", "iso9283_statistics"]


def iso9283_statistics(positions_mm: NDArray[np.float64]) -> dict[str, Any]:
    """``vap_mm`` (p,), ``rp_mm`` (p, 3), ``rp_max_mm`` (p,), ``ratio`` (p,) = vAP / max RP,
    ``barycentres_mm`` (p, 3, 3); from positions (p, 3 directions, cycles, 3)."""
    x = np.asarray(positions_mm, dtype=float)
    if x.ndim != 4 or x.shape[1] != 3 or x.shape[3] != 3 or x.shape[2] < 2:
        raise ValueError(f"positions must be (points, 3 directions, cycles >= 2, 3), got {x.shape}")
    bary = x.mean(axis=2)  # (p, 3, 3)
    gaps = np.linalg.norm(bary[:, :, None, :] - bary[:, None, :, :], axis=-1)
    vap = gaps.max(axis=(1, 2))
    dist = np.linalg.norm(x - bary[:, :, None, :], axis=-1)  # (p, 3, cycles)
    rp = dist.mean(axis=-1) + 3.0 * dist.std(axis=-1, ddof=1)
    rp_max = rp.max(axis=1)
    return {
        "vap_mm": vap.tolist(),
        "rp_mm": rp.tolist(),
        "rp_max_mm": rp_max.tolist(),
        "ratio": (vap / rp_max).tolist(),
        "barycentres_mm": bary.tolist(),
    }


def histogram(
    values_by_name: dict[str, NDArray[np.float64]], width_mm: float | None = None
) -> dict[str, Any]:
    """Frequency histograms (seed 000 Fig. 11) of several error lists on shared bins from 0.

    The bin width is ``width_mm`` or a round number giving about 16 bins up to the largest value.
    Returns ``edges_mm`` (k+1,) and ``counts`` {name: (k,)} (relative frequencies in ``share``).
    """
    arrays = {k: np.asarray(v, dtype=float) for k, v in values_by_name.items()}
    top = max((float(a.max()) for a in arrays.values() if a.size), default=1.0)
    if width_mm is None:
        raw = max(top, 1e-6) / 16.0
        mag = 10.0 ** np.floor(np.log10(raw))
        width_mm = float(min(s * mag for s in (1.0, 2.0, 2.5, 5.0, 10.0) if s * mag >= raw))
    k = max(1, int(np.ceil(top / width_mm - 1e-9)))
    if k * width_mm < top:
        k += 1
    edges = np.arange(k + 1) * width_mm
    counts = {name: np.histogram(a, bins=edges)[0] for name, a in arrays.items()}
    return {
        "edges_mm": edges.round(9).tolist(),
        "counts": {name: c.tolist() for name, c in counts.items()},
        "share": {name: (c / max(1, c.sum())).round(6).tolist() for name, c in counts.items()},
    }
