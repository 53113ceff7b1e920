"""The simulated laser tracker: the TCP position with measurement noise, in a stated frame.

``tracker_T_base`` (4, 4) is the pose of the robot base frame in the tracker's own frame; the
identity means the tracker reports in the robot base frame (the frame was established beforehand,
as in seed 000). Noise is independent, normal, ``sigma_mm`` per axis (default 0.01 mm).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.so3 import rotvec_to_matrix

__all__ = ["DEFAULT_SIGMA_MM", "LaserTracker"]

DEFAULT_SIGMA_MM = 0.01


class LaserTracker:
    """Measures points given in the robot base frame; reports them in the tracker frame with noise."""

    def __init__(
        self,
        sigma_mm: float = DEFAULT_SIGMA_MM,
        tracker_T_base: NDArray[np.float64] | None = None,
        seed: int = 0,
    ) -> None:
        if not (sigma_mm >= 0.0 and np.isfinite(sigma_mm)):
            raise ValueError(f"sigma_mm: must be a finite number >= 0, got {sigma_mm!r}")
        frame = np.eye(4) if tracker_T_base is None else np.array(tracker_T_base, dtype=float)
        if frame.shape != (4, 4) or not np.allclose(frame[:3, :3] @ frame[:3, :3].T, np.eye(3), atol=1e-9):
            raise ValueError("tracker_T_base: expected a rigid (4, 4) transform")
        self.sigma_mm = float(sigma_mm)
        self.tracker_T_base = frame
        self._rng = np.random.default_rng(seed)

    def to_tracker_frame(self, base_p_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Exact (noise-free) transform of (n, 3) or (3,) points from the robot base frame."""
        p = np.asarray(base_p_mm, dtype=float)
        return p @ self.tracker_T_base[:3, :3].T + self.tracker_T_base[:3, 3]

    def measure_rotation(self, base_r: NDArray[np.float64], sigma_deg: float) -> NDArray[np.float64]:
        """A 6-DOF probe's orientation (3, 3 in the robot base frame) as the tracker reports it: in its
        frame, turned by a random rotation of ``sigma_deg`` per axis (a normal rotation vector)."""
        noise = rotvec_to_matrix(self._rng.standard_normal(3) * np.radians(sigma_deg))
        return np.asarray(noise @ self.tracker_T_base[:3, :3] @ np.asarray(base_r, dtype=float))

    def measure(self, base_p_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Measured positions (same shape as the input) in the tracker frame, mm."""
        p = self.to_tracker_frame(base_p_mm)
        return p + self._rng.standard_normal(p.shape) * self.sigma_mm
