"""``comp-daemon robot show|fk``: look at a robot description and its forward kinematics."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from comp_daemon.kinematics.forward import chain, gravity_torques_nm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import PRESETS, load_robot


def register(subparsers: argparse._SubParsersAction) -> None:
    robot = subparsers.add_parser("robot", help="robot descriptions: show one, compute forward kinematics")
    sub = robot.add_subparsers(dest="robot_command", metavar="ROBOT_COMMAND", required=True)

    show = sub.add_parser("show", help="print a robot description as JSON")
    show.add_argument("robot", metavar="ROBOT", help=f"preset ({', '.join(PRESETS)}) or path to a TOML file")
    show.set_defaults(func=_show)

    fk = sub.add_parser(
        "fk", help="flange and TCP position and static gravity torques for one set of axis values"
    )
    fk.add_argument("robot", metavar="ROBOT", help=f"preset ({', '.join(PRESETS)}) or path to a TOML file")
    fk.add_argument("axes", metavar="A", type=float, nargs=6, help="axis values A1..A6 in deg")
    fk.add_argument("--payload-kg", type=float, default=0.0, help="load at the TCP (kg, default 0)")
    fk.set_defaults(func=_fk)


def _show(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
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
