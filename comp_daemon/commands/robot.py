"""``comp-daemon robot show|fk``: look at a robot description and its forward kinematics.

``ROBOT`` is a preset, a TOML description, a TOML ``[urdf]`` wrapper or a URDF file
(:mod:`comp_daemon.robot.urdf`); ``robot show --format toml|urdf`` writes it in either form.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from comp_daemon.kinematics.forward import chain, gravity_torques_nm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import PRESETS, description_toml, load_robot
from comp_daemon.robot.urdf import description_urdf

ROBOT_HELP = f"preset ({', '.join(PRESETS)}), or path to a TOML or URDF file"


def register(subparsers: argparse._SubParsersAction) -> None:
    robot = subparsers.add_parser("robot", help="robot descriptions: show one, compute forward kinematics")
    sub = robot.add_subparsers(dest="robot_command", metavar="ROBOT_COMMAND", required=True)

    show = sub.add_parser("show", help="print a robot description (JSON, TOML or URDF)")
    show.add_argument("robot", metavar="ROBOT", help=ROBOT_HELP)
    show.add_argument(
        "--format",
        choices=("json", "toml", "urdf"),
        default="json",
        help="json (default, with source and sha256), toml (a description file), urdf (its kinematics)",
    )
    show.set_defaults(func=_show)

    fk = sub.add_parser(
        "fk", help="flange and TCP position and static gravity torques for one set of axis values"
    )
    fk.add_argument("robot", metavar="ROBOT", help=ROBOT_HELP)
    fk.add_argument("axes", metavar="A", type=float, nargs=6, help="axis values A1..A6 in deg")
    fk.add_argument("--payload-kg", type=float, default=0.0, help="load at the TCP (kg, default 0)")
    fk.set_defaults(func=_fk)


def _show(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    if args.format == "toml":
        print(description_toml(robot), end="")
        return 0
    if args.format == "urdf":
        print(description_urdf(robot, [f"{robot.name}, from {robot.source}"]), end="")
        return 0
    doc = robot.to_dict()
    doc["source"] = robot.source
    doc["sha256"] = robot.sha256
    print(json.dumps(doc, indent=2))
    return 0


def _fk(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    a_deg = np.array(args.axes, dtype=float)
    if not np.all(np.isfinite(a_deg)):
        raise ValueError("axis values must be finite numbers")
    if not math.isfinite(args.payload_kg) or args.payload_kg < 0:
        raise ValueError(f"--payload-kg must be a finite number >= 0, got {args.payload_kg}")
    limits = robot.axis_limits_deg
    outside = [
        f"A{i + 1}={a_deg[i]:g} outside [{limits[i, 0]:g}, {limits[i, 1]:g}]"
        for i in range(6)
        if not limits[i, 0] <= a_deg[i] <= limits[i, 1]
    ]
    if outside:
        raise ValueError("axis values outside the robot's limits: " + "; ".join(outside))
    params = KinematicParams.from_robot(robot)
    q = axes_deg_to_q_rad(a_deg[None, :], robot.sign)
    ch = chain(params, q)
    tau = gravity_torques_nm(params, q, robot.link_mass_kg, robot.link_com_mm, args.payload_kg, ch)
    out = {
        "flange_mm": [round(float(v), 6) for v in ch.world_T_frame[0, 6, :3, 3]],
        "tcp_mm": [round(float(v), 6) for v in ch.tcp_mm[0]],
        "gravity_torque_nm": [round(float(v), 3) for v in tau[0]],
    }
    print(json.dumps(out))
    return 0
