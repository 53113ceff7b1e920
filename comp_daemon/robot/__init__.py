"""Robot descriptions (TOML, or a URDF: :mod:`comp_daemon.robot.urdf`) and the shipped presets."""

from comp_daemon.robot.description import (
    PRESETS,
    Joint,
    RobotDescription,
    RobotDescriptionError,
    load_robot,
    parse_robot_toml,
)

__all__ = ["PRESETS", "Joint", "RobotDescription", "RobotDescriptionError", "load_robot", "parse_robot_toml"]
