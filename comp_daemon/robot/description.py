"""Robot descriptions: the TOML form of ``docs/robot-description.md``, loaded and
validated; a URDF, or a TOML ``[urdf]`` table pointing at one, is read by :mod:`comp_daemon.robot.urdf`
into the same :class:`~comp_daemon.robot.types.RobotDescription`.

A description is read once, at the edge, and turned into arrays for the numerics one layer up
(``comp_daemon.kinematics.params.KinematicParams.from_robot``; this package imports no kinematics).
Everything inside the package trusts a loaded description; everything that reads a file refuses it
with a message that names the joint and field at fault.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from comp_daemon.common.files import named_file, read_text
from comp_daemon.robot.types import (
    N_JOINTS,
    Joint,
    RobotDescription,
    RobotDescriptionError,
    check_keys,
    description_toml,
    number,
    vec3,
)
from comp_daemon.robot.urdf import load_urdf, parse_urdf_wrapper

__all__ = [
    "FLANGE_R_KUKA_TOOL",
    "MASSLESS_PRESETS",
    "PRESETS",
    "Joint",
    "RobotDescription",
    "RobotDescriptionError",
    "description_toml",
    "load_robot",
    "parse_robot_toml",
]

# KUKA's tool frame in the flange frame of the robot files (z out of the flange): x_tool = z_flange,
# y_tool = y_flange, z_tool = −x_flange, i.e. Ry(−90°). A target's A, B, C orient the KUKA tool frame;
# the flange orientation asked of the kinematics is kinematics.kuka_abc.flange_rotation_of_tool_abc.
FLANGE_R_KUKA_TOOL = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
FLANGE_R_KUKA_TOOL.setflags(write=False)

PRESETS: dict[str, str] = {
    "kr210": "KUKA KR 210 R2700 extra",
    "irb120": "ABB IRB 120",
    "mh6": "Yaskawa MOTOMAN-MH6",
    "motoman_mh6": "Yaskawa MOTOMAN-MH6",
    "ur3": "Universal Robots UR3",
    "ur5": "Universal Robots UR5",
    "ur10": "Universal Robots UR10",
    "ur3e": "Universal Robots UR3e",
    "ur5e": "Universal Robots UR5e",
    "ur10e": "Universal Robots UR10e",
    "ur16e": "Universal Robots UR16e",
}
#: presets without link masses: the gravity models (compliance, gravity torques) do not apply
MASSLESS_PRESETS: frozenset[str] = frozenset({"motoman_mh6"})


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


def parse_robot_toml(text: str, source: str = "<string>", directory: Path | None = None) -> RobotDescription:
    """Parse and validate the text of a robot description file; a file holding a ``[urdf]`` table
    describes the robot by a URDF (:func:`comp_daemon.robot.urdf.parse_urdf_wrapper`; its path is
    relative to ``directory``, default the working directory)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RobotDescriptionError(f"{source}: not valid TOML: {exc}") from None
    if "urdf" in doc:
        return parse_urdf_wrapper(doc, source, directory or Path.cwd())

    check_keys(doc, {"robot": "", "tool": "", "joint": ""}, source)
    robot = doc.get("robot")
    if not isinstance(robot, dict):
        raise RobotDescriptionError(f"{source}: missing table [robot]")
    check_keys(robot, {"name": "", "repeatability_mm": "mm"}, f"{source} [robot]")
    name = robot.get("name")
    if not isinstance(name, str) or not name.strip():
        raise RobotDescriptionError(f"{source} [robot]: missing field 'name' (a non-empty string)")
    if "repeatability_mm" not in robot:
        raise RobotDescriptionError(f"{source} [robot]: missing field 'repeatability_mm'")
    repeatability = number(robot["repeatability_mm"], f"{source} [robot].repeatability_mm")
    if repeatability <= 0:
        raise RobotDescriptionError(f"{source} [robot].repeatability_mm: must be > 0, got {repeatability}")

    tool = doc.get("tool", {"xyz_mm": [0.0, 0.0, 0.0]})
    if not isinstance(tool, dict):
        raise RobotDescriptionError(f"{source}: [tool] must be a table")
    check_keys(tool, {"xyz_mm": "mm"}, f"{source} [tool]")
    tool_xyz = vec3(tool.get("xyz_mm", [0.0, 0.0, 0.0]), f"{source} [tool].xyz_mm")

    joints_raw = doc.get("joint")
    if not isinstance(joints_raw, list):
        raise RobotDescriptionError(f"{source}: missing [[joint]] tables (six expected)")
    if len(joints_raw) != N_JOINTS:
        raise RobotDescriptionError(f"{source}: {len(joints_raw)} [[joint]] tables; six joints are expected")
    joints = []
    for index, raw in enumerate(joints_raw, start=1):
        where = f"{source} joint {index}"
        check_keys(raw, _JOINT_FIELDS, where)
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
            a_mm=number(values["a_mm"], f"{where}.a_mm"),
            alpha_deg=number(values["alpha_deg"], f"{where}.alpha_deg"),
            d_mm=number(values["d_mm"], f"{where}.d_mm"),
            beta_deg=number(values["beta_deg"], f"{where}.beta_deg"),
            sign=int(sign),
            offset_deg=number(values["offset_deg"], f"{where}.offset_deg"),
            min_deg=number(values["min_deg"], f"{where}.min_deg"),
            max_deg=number(values["max_deg"], f"{where}.max_deg"),
            mass_kg=number(values["mass_kg"], f"{where}.mass_kg"),
            com_mm=vec3(values["com_mm"], f"{where}.com_mm"),
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
    """Load a preset by name (:data:`PRESETS`) or a description file by path: a TOML description,
    a TOML ``[urdf]`` wrapper, or a URDF (``.urdf``; :mod:`comp_daemon.robot.urdf`).

    ``motoman_mh6`` is seed 003's MH6 as the spec gives it (B.1, probe (40, 0, 100) mm, no masses);
    ``mh6`` the same geometry with a probe at (40, 0, 120) mm and approximate link masses, for the
    gravity models and the simulated MH6 cell."""
    key = str(name_or_path)
    if key in PRESETS:
        text = resources.files("comp_daemon.robot").joinpath(f"presets/{key}.toml").read_text("utf-8")
        return parse_robot_toml(text, source=f"preset:{key}")
    path = named_file(key, PRESETS, "robot", RobotDescriptionError)
    if path.suffix.lower() == ".urdf":
        return load_urdf(path)
    text = read_text(path, RobotDescriptionError)
    return parse_robot_toml(text, source=str(path), directory=path.parent)
