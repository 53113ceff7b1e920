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

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "BASE_FRAME_MAX_RMS_MM",
    "SCALE_RANGE",
    "FrameChange",
    "detect_frame",
    "frame_changes",
    "rigid_registration",
    "scale_problem",
    "transform_points",
]

BASE_FRAME_MAX_RMS_MM = 50.0
#: the measured positions' spread over the nominal ones' outside this range is not a robot in mm
SCALE_RANGE = (0.5, 2.0)
#: below this nominal spread (mm, RMS about the centroid) the ratio says too little to refuse on
SCALE_MIN_SPREAD_MM = 20.0


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
        raise ValueError(
            "the TCP positions lie (nearly) on a line (collinear) or at one point: the rotation between the "
            "tracker's frame and the robot's is not determined (measure poses spread over the workspace)"
        )
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


def _spread_mm(p: NDArray[np.float64]) -> float:
    """RMS distance of the points from their centroid (invariant under a rigid motion)."""
    q = np.asarray(p, dtype=float)
    return float(np.sqrt(np.mean(np.sum((q - q.mean(axis=0)) ** 2, axis=1))))


def scale_problem(p_nominal_base_mm: NDArray[np.float64], p_measured_mm: NDArray[np.float64]) -> str | None:
    """A sentence when the measured positions cannot be millimetres of this robot, else None.

    A rigid motion (any tracker frame) keeps the spread of the points about their centroid, and a
    calibration changes it by far less than a factor of two; positions in metres (1/1000),
    centimetres (1/10) or inches (1/25.4) do not. The calibration could otherwise absorb the scale
    in its link lengths and report a perfect fit of a robot a thousand times too small. Not judged
    when the nominal positions spread less than :data:`SCALE_MIN_SPREAD_MM`.
    """
    nominal, measured = _spread_mm(p_nominal_base_mm), _spread_mm(p_measured_mm)
    if nominal < SCALE_MIN_SPREAD_MM:
        return None
    ratio = measured / nominal
    if SCALE_RANGE[0] <= ratio <= SCALE_RANGE[1]:
        return None
    guesses = {"metres": 1e-3, "centimetres": 0.1, "inches": 1 / 25.4, "micrometres": 1e3}
    unit, factor = min(guesses.items(), key=lambda kv: abs(np.log(ratio / kv[1])))
    hint = f" (in {unit}?)" if abs(np.log(ratio / factor)) < np.log(1.5) else ""
    if hint and unit == "metres":
        hint += "; a file in metres is read with --units m,deg (or m,rad)"
    if ratio > 1.0:
        hint += (
            "; or rows from several tracker set-ups, each in its own frame: name them in a station "
            "column (docs/data-format.md)"
        )
    return (
        f"the measured x, y, z spread {ratio:.3g} times as far as the nominal TCP positions of the same "
        f"axis values ({measured:.4g} mm against {nominal:.4g} mm RMS about their centroids): they are "
        f"not millimetres of this robot{hint}; the campaign format (docs/data-format.md) asks for mm"
    )


#: a station's check error above this multiple of the other stations' is a jump
JUMP_FACTOR = 2.0
#: a rigid motion of the station's check rows alone that removes more than this share of their
#: squared error makes the jump a frame change
FRAME_CHANGE_SHARE = 0.5


@dataclass(frozen=True)
class FrameChange:
    """One station's check rows against the others': their error, and what a rigid motion of them
    alone leaves (``registered_rms_mm``). ``changed``: the error jumps and the motion removes it."""

    station: str
    rows: int
    rms_mm: float
    others_rms_mm: float
    registered_rms_mm: float
    angle_deg: float
    shift_mm: float
    changed: bool

    def describe(self) -> str:
        return (
            f"station {self.station}: its {self.rows} check rows are {self.rms_mm:.3f} mm RMS off against "
            f"{self.others_rms_mm:.3f} mm on the other stations' check rows; a rigid motion of them alone "
            f"({self.angle_deg:.3f}°, {self.shift_mm:.3f} mm at the origin) leaves "
            f"{self.registered_rms_mm:.3f} mm: "
            f"station {self.station}'s frame changed (the tracker moved during its session), not an effect "
            "of the robot"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "rows": self.rows,
            "rms_mm": round(self.rms_mm, 6),
            "others_rms_mm": round(self.others_rms_mm, 6),
            "registered_rms_mm": round(self.registered_rms_mm, 6),
            "angle_deg": round(self.angle_deg, 6),
            "shift_mm": round(self.shift_mm, 6),
            "frame_changed": self.changed,
        }


def frame_changes(
    station: Sequence[str], predicted_mm: NDArray[np.float64], measured_mm: NDArray[np.float64]
) -> list[FrameChange]:
    """Each station's check rows (``station`` (n,) names, the model's ``predicted_mm`` and the
    ``measured_mm`` (n, 3) of those rows) judged against the other stations' (:class:`FrameChange`);
    empty with fewer than two stations. A station with fewer than 4 rows is not judged."""
    names = np.asarray(station, dtype=str)
    err2 = np.sum((np.asarray(measured_mm) - np.asarray(predicted_mm)) ** 2, axis=1)
    labels = sorted(set(names.tolist()))
    out: list[FrameChange] = []
    if len(labels) < 2:
        return out
    for label in labels:
        own = names == label
        if own.sum() < 4:
            continue
        rms = float(np.sqrt(np.mean(err2[own])))
        others = float(np.sqrt(np.mean(err2[~own])))
        try:
            t = rigid_registration(predicted_mm[own], measured_mm[own])
        except ValueError:
            continue
        moved = transform_points(t, predicted_mm[own])
        after = float(np.sqrt(np.mean(np.sum((measured_mm[own] - moved) ** 2, axis=1))))
        angle = float(np.degrees(np.arccos(np.clip((np.trace(t[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
        changed = rms > JUMP_FACTOR * others and after**2 < (1.0 - FRAME_CHANGE_SHARE) * rms**2
        out.append(
            FrameChange(
                label, int(own.sum()), rms, others, after, angle, float(np.linalg.norm(t[:3, 3])), changed
            )
        )
    return out
