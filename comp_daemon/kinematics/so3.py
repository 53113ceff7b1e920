"""SO(3) conversions, in one place: skew matrices, rotation vectors ↔ matrices, unit quaternions ↔
matrices, the left Jacobian.

Batch-first: every function takes (…, 3) rotation vectors (rad) or (…, 3, 3) matrices and keeps the
leading shape. Rotation vectors are axis × angle (rad), Rodrigues' formula.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "left_jacobian",
    "matrix_to_quat",
    "matrix_to_rotvec",
    "quat_to_matrix",
    "rotvec_to_matrix",
    "skew",
]

FloatArray = NDArray[np.float64]


def skew(v: FloatArray) -> FloatArray:
    """(…, 3, 3) cross-product matrices ``[v]×`` of vectors (…, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotvec_to_matrix(rotvec: FloatArray) -> FloatArray:
    """(…, 3, 3) rotation matrices of rotation vectors (…, 3) (rad)."""
    r = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(r, axis=-1)
    k = skew(r / np.where(angle > 1e-300, angle, 1.0)[..., None])
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def matrix_to_rotvec(rot: FloatArray) -> FloatArray:
    """(…, 3) rotation vectors (rad) of rotation matrices (…, 3, 3); angle in [0, π]."""
    r = np.asarray(rot, dtype=float)
    angle = np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))
    axis = np.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], axis=-1
    )
    s = 2.0 * np.sin(angle)
    small = angle <= 1e-12
    out = np.where(small[..., None], 0.0, axis / np.where(small, 1.0, s)[..., None] * angle[..., None])
    near_pi = angle > np.pi - 1e-6
    if np.any(near_pi):  # sin(angle) → 0: the axis from the symmetric part, R = 2 k kᵀ − I at π
        sym = (r[near_pi] + np.eye(3)) / 2.0
        col = np.argmax(np.diagonal(sym, axis1=-2, axis2=-1), axis=-1)
        k = sym[np.arange(len(col)), :, col]
        k = k / np.linalg.norm(k, axis=-1, keepdims=True)
        sign = np.where(np.sum(k * axis[near_pi], axis=-1) < 0, -1.0, 1.0)
        out[near_pi] = k * (sign * angle[near_pi])[..., None]
    return out


def left_jacobian(rotvec: FloatArray) -> FloatArray:
    """(…, 3, 3) left Jacobian of SO(3): ``d/dr (R(r)·v) = −[R(r)·v]× · J_l(r)``."""
    r = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(r, axis=-1)[..., None, None]
    k = skew(r)
    kk = k @ k
    small = angle < 1e-6
    safe = np.where(small, 1.0, angle)
    big = np.eye(3) + (1.0 - np.cos(safe)) / safe**2 * k + (safe - np.sin(safe)) / safe**3 * kk
    return np.where(small, np.eye(3) + 0.5 * k + kk / 6.0, big)


def quat_to_matrix(q_wxyz: FloatArray) -> FloatArray:
    """(n, 3, 3) rotation matrices of unit quaternions (n, 4), w first."""
    return np.asarray(Rotation.from_quat(np.asarray(q_wxyz, dtype=float), scalar_first=True).as_matrix())


def matrix_to_quat(rot: FloatArray) -> FloatArray:
    """(n, 4) unit quaternions (w first, w ≥ 0) of rotation matrices (n, 3, 3)."""
    q = np.asarray(Rotation.from_matrix(np.asarray(rot, dtype=float)).as_quat(scalar_first=True))
    return np.where(q[..., :1] < 0, -q, q)
