"""Rigid registration of the measurement frame (Kabsch / Umeyama without scale).

A laser tracker measures in its own frame ``world``. Before a calibration iterates, the robot's base
frame is placed in that frame by the rigid motion that best maps the nominal TCP positions (robot
base frame, mm) onto the measured ones: ``world_T_base = argmin Σ |R·p_nominal + t − p_measured|²``
over rotations R (det +1) and translations t, solved in closed form by the SVD of the
cross-covariance (Kabsch; Umeyama's reflection guard). The calibration then refines this frame
together with the other parameters.

:func:`detect_frame` decides whether a data set is already in the robot base frame: the nominal
model misses a real robot by millimetres, a tracker frame is off by far more than
:data:`BASE_FRAME_MAX_RMS_MM`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

__all__ = ["BASE_FRAME_MAX_RMS_MM", "detect_frame", "rigid_registration", "transform_points"]

BASE_FRAME_MAX_RMS_MM = 50.0


def rigid_registration(p_src_mm: NDArray[np.float64], p_dst_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """(4, 4) ``dst_T_src``: the rigid motion that best maps points ``p_src_mm`` (n, 3) onto ``p_dst_mm``."""
    src = np.asarray(p_src_mm, dtype=float)
    dst = np.asarray(p_dst_mm, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"point sets must both be (n, 3), got {src.shape} and {dst.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"a rigid registration needs at least 3 points, got {src.shape[0]}")
    c_src, c_dst = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - c_dst).T @ (src - c_src)
    u, sv, vt = np.linalg.svd(cov)
    if sv[1] <= 1e-12 * max(sv[0], 1e-300):
        raise ValueError("the points are (nearly) collinear: the rotation is not determined")
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = c_dst - rot @ c_src
    return out


def transform_points(a_T_b: NDArray[np.float64], p_b_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3) points given in frame b expressed in frame a."""
    return np.asarray(p_b_mm, dtype=float) @ a_T_b[:3, :3].T + a_T_b[:3, 3]


def detect_frame(
    p_nominal_base_mm: NDArray[np.float64], p_measured_mm: NDArray[np.float64]
) -> Literal["base", "tracker"]:
    """``"base"`` if the measurements lie within :data:`BASE_FRAME_MAX_RMS_MM` (RMS) of the nominal TCPs."""
    diff = np.asarray(p_measured_mm, dtype=float) - np.asarray(p_nominal_base_mm, dtype=float)
    rms = float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))
    return "base" if rms <= BASE_FRAME_MAX_RMS_MM else "tracker"
