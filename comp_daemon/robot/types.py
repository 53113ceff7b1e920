"""The robot description's types and the field checks its readers share (TOML and URDF).

:class:`RobotDescription` is what every reader returns (:func:`comp_daemon.robot.description.load_robot`);
:func:`number`, :func:`vec3` and :func:`check_keys` refuse a bad field naming its place.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "N_JOINTS",
    "Joint",
    "RobotDescription",
    "RobotDescriptionError",
    "check_keys",
    "description_toml",
    "number",
    "vec3",
]

N_JOINTS = 6
_UNIT_SUFFIXES = ("mm", "m", "cm", "um", "deg", "rad", "kg", "g", "lb", "in")


class RobotDescriptionError(ValueError):
    """A robot description file that cannot be used; the message names the place and the fault."""


@dataclass(frozen=True, slots=True)
class Joint:
    a_mm: float
    alpha_deg: float
    d_mm: float
    beta_deg: float
    sign: int
    offset_deg: float
    min_deg: float
    max_deg: float
    mass_kg: float
    com_mm: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class RobotDescription:
    """A validated robot: name, six joints, tool, repeatability; where it came from."""

    name: str
    repeatability_mm: float
    tool_xyz_mm: tuple[float, float, float]
    joints: tuple[Joint, ...]
    source: str

    # ---- arrays for the numerics -------------------------------------------------------------
    @property
    def axis_limits_deg(self) -> NDArray[np.float64]:
        """(6, 2) array of [min, max] axis values in the controller's convention."""
        return np.array([[j.min_deg, j.max_deg] for j in self.joints], dtype=float)

    @property
    def q_limits_rad(self) -> NDArray[np.float64]:
        """(6, 2) joint limits as [low, high] of q = sign·A (rad, DH sign)."""
        q = np.deg2rad(self.axis_limits_deg) * self.sign[:, None]
        return np.sort(q, axis=1)

    @property
    def sign(self) -> NDArray[np.float64]:
        return np.array([j.sign for j in self.joints], dtype=float)

    @property
    def offset_deg(self) -> NDArray[np.float64]:
        return np.array([j.offset_deg for j in self.joints], dtype=float)

    @property
    def link_mass_kg(self) -> NDArray[np.float64]:
        return np.array([j.mass_kg for j in self.joints], dtype=float)

    @property
    def link_com_mm(self) -> NDArray[np.float64]:
        """(6, 3): centre of mass of link i in frame i."""
        return np.array([j.com_mm for j in self.joints], dtype=float)

    def to_dict(self) -> dict[str, Any]:
        return {
            "robot": {"name": self.name, "repeatability_mm": self.repeatability_mm},
            "tool": {"xyz_mm": list(self.tool_xyz_mm)},
            "joint": [
                {
                    "a_mm": j.a_mm,
                    "alpha_deg": j.alpha_deg,
                    "d_mm": j.d_mm,
                    "beta_deg": j.beta_deg,
                    "sign": j.sign,
                    "offset_deg": j.offset_deg,
                    "min_deg": j.min_deg,
                    "max_deg": j.max_deg,
                    "mass_kg": j.mass_kg,
                    "com_mm": list(j.com_mm),
                }
                for j in self.joints
            ],
        }

    @property
    def sha256(self) -> str:
        """Hash of the description's content (not of its file's formatting or comments)."""
        canonical = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()


def description_toml(robot: RobotDescription) -> str:
    """The TOML text of a description (read back by :func:`parse_robot_toml` to the same values:
    numbers are written with ``repr``, the shortest text of the same double)."""

    def text(value: Any) -> str:
        if isinstance(value, str):
            return json.dumps(value)  # a JSON string is a TOML basic string
        if isinstance(value, list | tuple):
            return "[" + ", ".join(text(v) for v in value) + "]"
        return repr(value)

    doc = robot.to_dict()
    lines = [
        f"# {robot.name}, from {robot.source}",
        "# Convention: theta_i = sign_i * A_i + offset_i;",
        "# T_{i-1,i} = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i) (mm, deg, kg)",
        "",
        "[robot]",
        *(f"{k} = {text(v)}" for k, v in doc["robot"].items()),
        "",
        "[tool]",
        *(f"{k} = {text(v)}" for k, v in doc["tool"].items()),
    ]
    for joint in doc["joint"]:
        lines += ["", "[[joint]]", *(f"{k} = {text(v)}" for k, v in joint.items())]
    return "\n".join(lines) + "\n"


def number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RobotDescriptionError(f"{where}: expected a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise RobotDescriptionError(f"{where}: expected a finite number, got {value!r}")
    return out


def vec3(value: Any, where: str) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise RobotDescriptionError(f"{where}: expected a list of three numbers, got {value!r}")
    x, y, z = (number(v, f"{where}[{k}]") for k, v in enumerate(value))
    return (x, y, z)


def _stem_and_unit(key: str) -> tuple[str, str]:
    for suffix in _UNIT_SUFFIXES:
        if key.endswith("_" + suffix):
            return key[: -len(suffix) - 1], suffix
    return key, ""


def check_keys(table: dict[str, Any], allowed: dict[str, str], where: str) -> None:
    by_stem = {_stem_and_unit(k)[0]: k for k in allowed}
    for key in table:
        if key in allowed:
            continue
        stem, unit = _stem_and_unit(key)
        if stem in by_stem:
            expected = by_stem[stem]
            raise RobotDescriptionError(
                f"{where}: field '{key}' is in {unit or 'no unit'}; this format expects '{expected}' "
                f"(in {allowed[expected] or 'no unit'})"
            )
        raise RobotDescriptionError(f"{where}: unknown field '{key}' (allowed: {', '.join(allowed)})")
