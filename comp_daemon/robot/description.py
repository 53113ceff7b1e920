"""Robot descriptions: the TOML form of ``docs/robot-description.md``, loaded and validated.

A description is read once, at the edge, and turned into arrays for the numerics one layer up
(``comp_daemon.kinematics.params.KinematicParams.from_robot``; this package imports no kinematics).
Everything inside the package trusts a loaded description; everything that reads a file refuses it
with a message that names the joint and field at fault.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "FLANGE_R_KUKA_TOOL",
    "MASSLESS_PRESETS",
    "PRESETS",
    "Joint",
    "RobotDescription",
    "RobotDescriptionError",
    "load_robot",
    "parse_robot_toml",
]

# KUKA's tool frame in the flange frame of the robot files (z out of the flange): x_tool = z_flange,
# y_tool = y_flange, z_tool = −x_flange, i.e. Ry(−90°). A target's A, B, C orient the KUKA tool frame;
# the flange orientation asked of the kinematics is rotation_kuka_abc_deg(abc) @ FLANGE_R_KUKA_TOOL.T.
FLANGE_R_KUKA_TOOL = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
FLANGE_R_KUKA_TOOL.setflags(write=False)

PRESETS: dict[str, str] = {
    "kr210": "KUKA KR 210 R2700 extra",
    "irb120": "ABB IRB 120",
    "mh6": "Yaskawa MOTOMAN-MH6",
    "motoman_mh6": "Yaskawa MOTOMAN-MH6",
}
#: presets without link masses: the gravity models (compliance, gravity torques) do not apply
MASSLESS_PRESETS: frozenset[str] = frozenset({"motoman_mh6"})

N_JOINTS = 6

# field -> unit suffix it must carry; a field with the same stem and another unit is refused by name
_JOINT_FIELDS: dict[str, str] = {
    "a_mm": "mm",
    "alpha_deg": "deg",
    "d_mm": "mm",
    "beta_deg": "deg",
    "sign": "",
    "offset_deg": "deg",
    "min_deg": "deg",
    "max_deg": "deg",
    "mass_kg": "kg",
    "com_mm": "mm",
}
_OPTIONAL_JOINT_FIELDS = {"beta_deg": 0.0, "mass_kg": 0.0, "com_mm": [0.0, 0.0, 0.0]}
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


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RobotDescriptionError(f"{where}: expected a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise RobotDescriptionError(f"{where}: expected a finite number, got {value!r}")
    return out


def _vec3(value: Any, where: str) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise RobotDescriptionError(f"{where}: expected a list of three numbers, got {value!r}")
    x, y, z = (_number(v, f"{where}[{k}]") for k, v in enumerate(value))
    return (x, y, z)


def _stem_and_unit(key: str) -> tuple[str, str]:
    for suffix in _UNIT_SUFFIXES:
        if key.endswith("_" + suffix):
            return key[: -len(suffix) - 1], suffix
    return key, ""


def _check_keys(table: dict[str, Any], allowed: dict[str, str], where: str) -> None:
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


def parse_robot_toml(text: str, source: str = "<string>") -> RobotDescription:
    """Parse and validate the text of a robot description file."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RobotDescriptionError(f"{source}: not valid TOML: {exc}") from None

    _check_keys(doc, {"robot": "", "tool": "", "joint": ""}, source)
    robot = doc.get("robot")
    if not isinstance(robot, dict):
        raise RobotDescriptionError(f"{source}: missing table [robot]")
    _check_keys(robot, {"name": "", "repeatability_mm": "mm"}, f"{source} [robot]")
    name = robot.get("name")
    if not isinstance(name, str) or not name.strip():
        raise RobotDescriptionError(f"{source} [robot]: missing field 'name' (a non-empty string)")
    if "repeatability_mm" not in robot:
        raise RobotDescriptionError(f"{source} [robot]: missing field 'repeatability_mm'")
    repeatability = _number(robot["repeatability_mm"], f"{source} [robot].repeatability_mm")
    if repeatability <= 0:
        raise RobotDescriptionError(f"{source} [robot].repeatability_mm: must be > 0, got {repeatability}")

    tool = doc.get("tool", {"xyz_mm": [0.0, 0.0, 0.0]})
    if not isinstance(tool, dict):
        raise RobotDescriptionError(f"{source}: [tool] must be a table")
    _check_keys(tool, {"xyz_mm": "mm"}, f"{source} [tool]")
    tool_xyz = _vec3(tool.get("xyz_mm", [0.0, 0.0, 0.0]), f"{source} [tool].xyz_mm")

    joints_raw = doc.get("joint")
    if not isinstance(joints_raw, list):
        raise RobotDescriptionError(f"{source}: missing [[joint]] tables (six expected)")
    if len(joints_raw) != N_JOINTS:
        raise RobotDescriptionError(f"{source}: {len(joints_raw)} [[joint]] tables; six joints are expected")
    joints = []
    for index, raw in enumerate(joints_raw, start=1):
        where = f"{source} joint {index}"
        _check_keys(raw, _JOINT_FIELDS, where)
        values: dict[str, Any] = {}
        for field in _JOINT_FIELDS:
            if field not in raw:
                if field in _OPTIONAL_JOINT_FIELDS:
                    values[field] = _OPTIONAL_JOINT_FIELDS[field]
                    continue
                raise RobotDescriptionError(f"{where}: missing field '{field}'")
            values[field] = raw[field]
        sign = values["sign"]
        if sign not in (1, -1) or isinstance(sign, bool):
            raise RobotDescriptionError(f"{where}.sign: must be 1 or -1, got {sign!r}")
        joint = Joint(
            a_mm=_number(values["a_mm"], f"{where}.a_mm"),
            alpha_deg=_number(values["alpha_deg"], f"{where}.alpha_deg"),
            d_mm=_number(values["d_mm"], f"{where}.d_mm"),
            beta_deg=_number(values["beta_deg"], f"{where}.beta_deg"),
            sign=int(sign),
            offset_deg=_number(values["offset_deg"], f"{where}.offset_deg"),
            min_deg=_number(values["min_deg"], f"{where}.min_deg"),
            max_deg=_number(values["max_deg"], f"{where}.max_deg"),
            mass_kg=_number(values["mass_kg"], f"{where}.mass_kg"),
            com_mm=_vec3(values["com_mm"], f"{where}.com_mm"),
        )
        if joint.min_deg >= joint.max_deg:
            raise RobotDescriptionError(
                f"{where}: min_deg ({joint.min_deg}) must be below max_deg ({joint.max_deg})"
            )
        if joint.mass_kg < 0:
            raise RobotDescriptionError(f"{where}.mass_kg: must be >= 0, got {joint.mass_kg}")
        joints.append(joint)
    return RobotDescription(
        name=name.strip(),
        repeatability_mm=repeatability,
        tool_xyz_mm=tool_xyz,
        joints=tuple(joints),
        source=source,
    )


def load_robot(name_or_path: str | Path) -> RobotDescription:
    """Load a preset by name (``kr210``, ``irb120``, ``mh6``, ``motoman_mh6``) or a description file by path.

    ``motoman_mh6`` is seed 003's MH6 as the spec gives it (B.1, probe (40, 0, 100) mm, no masses);
    ``mh6`` the same geometry with a probe at (40, 0, 120) mm and approximate link masses, for the
    gravity models and the simulated MH6 cell."""
    key = str(name_or_path)
    if key in PRESETS:
        text = resources.files("comp_daemon.robot").joinpath(f"presets/{key}.toml").read_text("utf-8")
        return parse_robot_toml(text, source=f"preset:{key}")
    path = Path(key)
    if not path.is_file():
        raise RobotDescriptionError(
            f"robot '{key}': neither a preset ({', '.join(PRESETS)}) nor a readable file"
        )
    try:
        text = path.read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RobotDescriptionError(f"{path}: cannot read: {exc}") from None
    return parse_robot_toml(text, source=str(path))
