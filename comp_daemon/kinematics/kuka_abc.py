"""KUKA ``A, B, C`` angles and the flange rotation they ask for: the one place of the convention.

* ``A, B, C`` (deg) are KUKA's ``Rz(A)·Ry(B)·Rx(C)``: A about z, then B about the new y, then C about
  the newest x (intrinsic Z-Y'-X''; SciPy's ``Rotation.from_euler("ZYX", [A, B, C], degrees=True)``).
  :func:`abc_deg_to_matrix` and :func:`matrix_to_abc_deg` convert, for any frame (a target's tool, a
  tracker's base, a KRL ``FRAME``).
* A target's (or a listing's) ``A, B, C`` orient KUKA's **tool** frame, whose x is the flange's z
  (:data:`~comp_daemon.robot.description.FLANGE_R_KUKA_TOOL`); the kinematics work with the
  **flange** rotation. :func:`flange_rotation_of_tool_abc` and :func:`tool_abc_of_flange_rotation`
  go between the two, and every door (HTTP targets, target files, ``compensate``, ``export``, the
  simulated campaign) calls them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.robot.description import FLANGE_R_KUKA_TOOL

__all__ = [
    "abc_deg_to_matrix",
    "flange_rotation_of_tool_abc",
    "matrix_to_abc_deg",
    "tool_abc_of_flange_rotation",
]


def abc_deg_to_matrix(abc_deg: ArrayLike) -> NDArray[np.float64]:
    """(…, 3, 3) rotation matrices ``Rz(A)·Ry(B)·Rx(C)`` of KUKA ``A, B, C`` (…, 3) in deg."""
    abc = np.deg2rad(np.asarray(abc_deg, dtype=float))
    if abc.ndim == 0 or abc.shape[-1] != 3:
        raise ValueError(f"KUKA A, B, C need 3 angles per frame, got shape {abc.shape}")
    ca, sa = np.cos(abc[..., 0]), np.sin(abc[..., 0])
    cb, sb = np.cos(abc[..., 1]), np.sin(abc[..., 1])
    cc, sc = np.cos(abc[..., 2]), np.sin(abc[..., 2])
    r = np.empty((*abc.shape[:-1], 3, 3))
    r[..., 0, 0] = ca * cb
    r[..., 0, 1] = ca * sb * sc - sa * cc
    r[..., 0, 2] = ca * sb * cc + sa * sc
    r[..., 1, 0] = sa * cb
    r[..., 1, 1] = sa * sb * sc + ca * cc
    r[..., 1, 2] = sa * sb * cc - ca * sc
    r[..., 2, 0] = -sb
    r[..., 2, 1] = cb * sc
    r[..., 2, 2] = cb * cc
    return r


def matrix_to_abc_deg(rot: ArrayLike) -> NDArray[np.float64]:
    """(…, 3) KUKA ``A, B, C`` (deg) of rotation matrices (…, 3, 3), ``Rz(A)·Ry(B)·Rx(C)``.

    ``B`` from ``atan2(−r31, hypot(r11, r21))`` (accurate at every angle); at ``B = ±90°`` (gimbal
    lock) only ``A ∓ C`` is defined and ``C`` is set to 0.
    """
    r = np.asarray(rot, dtype=float)
    if r.ndim < 2 or r.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must be (…, 3, 3), got shape {r.shape}")
    cb = np.hypot(r[..., 0, 0], r[..., 1, 0])
    b = np.arctan2(-r[..., 2, 0], cb)
    locked = cb < 1e-12
    a = np.where(locked, np.arctan2(-r[..., 0, 1], r[..., 1, 1]), np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    c = np.where(locked, 0.0, np.arctan2(r[..., 2, 1], r[..., 2, 2]))
    return np.degrees(np.stack([a, b, c], axis=-1))


def flange_rotation_of_tool_abc(abc_deg: ArrayLike) -> NDArray[np.float64]:
    """(…, 3, 3) flange rotation (robot files' flange frame, z out of the flange) that puts KUKA's
    tool frame at ``A, B, C`` (…, 3) deg."""
    return abc_deg_to_matrix(abc_deg) @ FLANGE_R_KUKA_TOOL.T


def tool_abc_of_flange_rotation(flange_r: ArrayLike) -> NDArray[np.float64]:
    """(…, 3) KUKA ``A, B, C`` (deg) of the tool frame of flange rotations (…, 3, 3); the inverse of
    :func:`flange_rotation_of_tool_abc`."""
    return matrix_to_abc_deg(np.asarray(flange_r, dtype=float) @ FLANGE_R_KUKA_TOOL)
