"""Frames and numbers as controller listings write them: KUKA A, B, C, ABB quaternions, exact decimals.

* ``A, B, C`` (deg): KUKA's ``Rz(A)·Ry(B)·Rx(C)``, converted by :mod:`comp_daemon.kinematics.kuka_abc`;
* quaternions ``q1..q4`` = ``w, x, y, z`` (ABB's order), unit, ``q1 ≥ 0``;
* rotation vectors in degrees (axis × angle) for the CSV listings;
* numbers as the shortest decimal text (no exponent) that reads back to the same double
  (:func:`num`), so that a listing read back gives the values it was written from.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.so3 import rotvec_to_matrix

__all__ = [
    "FloatArray",
    "frame",
    "matrix_to_quaternion",
    "matrix_to_rotvec_deg",
    "num",
    "quaternion_to_matrix",
    "rigid_inverse",
    "rotvec_deg_to_matrix",
]

FloatArray = NDArray[np.float64]


def num(value: float) -> str:
    """``value`` as positional decimal text that reads back (``float``) to the same double."""
    v = float(value) + 0.0  # no "-0.0"
    if not np.isfinite(v):
        raise ValueError(f"cannot list a non-finite number ({v})")
    return np.format_float_positional(v, unique=True, trim="0")


def frame(p_mm: FloatArray, rot: FloatArray) -> FloatArray:
    """The 4×4 homogeneous transform of a position (mm) and a rotation matrix."""
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = p_mm
    return out


def rigid_inverse(t: FloatArray) -> FloatArray:
    """Inverse of a rigid 4×4 transform (transpose of the rotation, no general inversion)."""
    rot = np.asarray(t, dtype=float)[:3, :3]
    return frame(-rot.T @ np.asarray(t, dtype=float)[:3, 3], rot.T)


def matrix_to_quaternion(rot: FloatArray) -> FloatArray:
    """(…, 4) unit quaternions ``w, x, y, z`` (``w ≥ 0``) of rotation matrices (…, 3, 3).

    Shepperd's method: the largest of ``w, x, y, z`` is taken from the diagonal, the others from
    the off-diagonal sums, so every branch divides by at least one half.
    """
    r = np.asarray(rot, dtype=float)
    flat = r.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        k = int(np.argmax([tr, m[0, 0], m[1, 1], m[2, 2]]))
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
        qa = np.array(q)
        out[i] = qa / np.linalg.norm(qa) * (1.0 if qa[0] >= 0 else -1.0)
    return out.reshape(*r.shape[:-2], 4)


def quaternion_to_matrix(q: FloatArray) -> FloatArray:
    """(…, 3, 3) rotation matrices of quaternions ``w, x, y, z`` (…, 4), normalised first."""
    qa = np.asarray(q, dtype=float)
    qa = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    w, x, y, z = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def matrix_to_rotvec_deg(rot: FloatArray) -> FloatArray:
    """(…, 3) rotation vectors (axis × angle, deg, angle in [0, 180]) of rotation matrices, through
    the quaternion (``angle = 2·atan2(|v|, w)``: accurate at every angle, 180° included)."""
    q = matrix_to_quaternion(rot)
    v = q[..., 1:]
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(norm, q[..., :1])
    scale = np.where(norm > 0, angle / np.where(norm > 0, norm, 1.0), 2.0)
    return np.degrees(v * scale)


def rotvec_deg_to_matrix(rotvec_deg: FloatArray) -> FloatArray:
    """(…, 3, 3) rotation matrices of rotation vectors in deg."""
    return rotvec_to_matrix(np.radians(np.asarray(rotvec_deg, dtype=float)))
