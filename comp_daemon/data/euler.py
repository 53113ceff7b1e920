"""A 6-DOF probe's orientation written as Euler angles: the reader option ``--euler CONVENTION``.

Tracker software (and spreadsheets made from it) often exports a 6-DOF probe's orientation as
three angles instead of a quaternion. Which three rotations they are cannot be told from the
numbers, so the file is read only with a stated convention, never by guess:

- The angles are the columns ``e1, e2, e3``: the angle of the first, the second and the third
  rotation of the sequence, in that order (naming them by axis would be ambiguous for a sequence
  such as ``zyz``).
- ``CONVENTION`` is ``intrinsic-AXES`` or ``extrinsic-AXES`` with three axis letters from ``x, y,
  z`` (no letter twice in a row), optionally followed by ``-deg`` or ``-rad``:

  - ``intrinsic-zyx``: rotate by ``e1`` about z, then by ``e2`` about the *new* y, then by ``e3``
    about the newest x: ``R = Rz(e1)·Ry(e2)·Rx(e3)`` (KUKA's A, B, C and the yaw-pitch-roll of
    many probes);
  - ``extrinsic-xyz``: rotate by ``e1`` about the fixed x, then by ``e2`` about the fixed y, then
    by ``e3`` about the fixed z: ``R = Rz(e3)·Ry(e2)·Rx(e1)`` (the same rotation as
    ``intrinsic-zyx`` with ``e1`` and ``e3`` swapped).

  ``R`` turns the probe's axes into the frame of ``x, y, z``, as the quaternion columns do.
  A bare ``zyx`` is refused: the same letters give another rotation when read the other way.
- The angle unit is ``--units``' (degrees by default) unless the convention ends in ``-deg`` or
  ``-rad``, which then applies to ``e1, e2, e3`` alone.

At read time the three columns become ``qw, qx, qy, qz`` (w first, ``qw ≥ 0``), so everything
after the reader sees a quaternion; a file with both forms, or with ``e1, e2, e3`` read without the
option, is refused naming what to do.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

__all__ = ["EULER_COLUMNS", "EulerConvention", "euler_to_quaternion", "parse_euler"]

#: the angles of the first, second and third rotation of the stated sequence
EULER_COLUMNS: tuple[str, ...] = ("e1", "e2", "e3")

_FORM = re.compile(r"(intrinsic|extrinsic)-([xyz]{3})(?:-(deg|rad))?")
_AXIS = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True, slots=True)
class EulerConvention:
    """Three rotations about ``axes`` (``"zyx"``), about the moving axes (``intrinsic``) or the fixed
    ones; ``unit`` the angles' own unit, ``None`` for ``--units``' angle unit."""

    intrinsic: bool
    axes: str
    unit: Literal["deg", "rad"] | None = None

    @property
    def name(self) -> str:
        kind = "intrinsic" if self.intrinsic else "extrinsic"
        return f"{kind}-{self.axes}" + (f"-{self.unit}" if self.unit else "")

    def quaternions(self, e_deg: NDArray[np.float64]) -> NDArray[np.float64]:
        """(n, 4) unit quaternions (w, x, y, z; w ≥ 0) of angles ``e_deg`` (n, 3) in degrees."""
        return euler_to_quaternion(e_deg, self.axes, intrinsic=self.intrinsic)


def parse_euler(text: str) -> EulerConvention:
    """``"intrinsic-zyx"`` → :class:`EulerConvention`; ValueError naming what is wrong (module docstring)."""
    spec = text.strip().lower()
    found = _FORM.fullmatch(spec)
    if found is None:
        bare = re.fullmatch(r"([xyz]{3})(?:-(deg|rad))?", spec)
        if bare is not None:
            raise ValueError(
                f"--euler {text!r} is ambiguous: say whether the rotations are about the moving axes "
                f"(intrinsic-{bare.group(1)}; KUKA's A, B, C are intrinsic-zyx) or about the fixed axes "
                f"(extrinsic-{bare.group(1)})"
            )
        raise ValueError(
            f"--euler {text!r}: expected intrinsic-AXES or extrinsic-AXES with three of x, y, z "
            "(e.g. intrinsic-zyx), optionally ending in -deg or -rad"
        )
    kind, axes, unit = found.groups()
    if axes[0] == axes[1] or axes[1] == axes[2]:
        raise ValueError(
            f"--euler {text!r}: two rotations in a row about the same axis ({axes}) are one rotation; "
            "no Euler convention repeats an axis in a row"
        )
    own: Literal["deg", "rad"] | None = "deg" if unit == "deg" else "rad" if unit == "rad" else None
    return EulerConvention(intrinsic=kind == "intrinsic", axes=axes, unit=own)


def _multiply(p: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hamilton product of (n, 4) quaternions, w first."""
    pw, px, py, pz = p.T
    qw, qx, qy, qz = q.T
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=1,
    )


def euler_to_quaternion(e_deg: NDArray[np.float64], axes: str, *, intrinsic: bool) -> NDArray[np.float64]:
    """(n, 4) unit quaternions (w first, ``w ≥ 0``) of the rotations ``e_deg`` (n, 3), degrees,
    about ``axes`` in order: ``R = R1·R2·R3`` intrinsic, ``R = R3·R2·R1`` extrinsic."""
    half = np.radians(np.asarray(e_deg, dtype=float)) / 2.0
    n = half.shape[0]
    steps = []
    for k, axis in enumerate(axes):
        q = np.zeros((n, 4))
        q[:, 0] = np.cos(half[:, k])
        q[:, 1 + _AXIS[axis]] = np.sin(half[:, k])
        steps.append(q)
    first, second, third = steps if intrinsic else steps[::-1]
    out = _multiply(_multiply(first, second), third)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(out[:, :1] < 0.0, -out, out)
