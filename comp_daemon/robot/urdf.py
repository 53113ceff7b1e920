"""URDF robots: read a URDF's serial chain into a :class:`RobotDescription`, compute its forward
kinematics, and write a description's kinematics back as URDF text.

The XML is parsed with the standard library's :mod:`xml.etree.ElementTree` (no ROS packages;
``xacro`` files must be expanded first: ``xacro robot.urdf.xacro > robot.urdf``). Only what the
kinematics needs is read: links (with ``<inertial>`` mass and origin), joints (type, parent,
child, ``<origin xyz rpy>``, ``<axis>``, ``<limit lower upper>``). Lengths in a URDF are metres,
angles radians; the description is mm and degrees.

**The chain.** From ``base_link`` (default: the root of the URDF's tree) to ``tip_link`` (default:
``tool0`` where the URDF has it, the ROS-Industrial flange frame with z out of the flange; else
the one leaf the chain ends in). The path may pass fixed joints either way (``base`` below
``base_link`` in the UR descriptions) and must hold exactly six revolute (or continuous) joints,
no prismatic, floating or planar one.

**Axis values.** The controller's axis value ``A_i`` (deg) and the URDF joint position ``q_i``
(rad) are related by ``q_i = radians(axis_sign_i · A_i + axis_offset_deg_i)``; by default
``axis_sign = +1`` and ``axis_offset_deg = 0`` (the controller shows the URDF's joint values, as
UR and the ROS-Industrial KUKA, ABB and Yaskawa descriptions do). A robot whose controller
differs states both in a wrapper TOML (``[urdf]``, :func:`parse_urdf_wrapper`).

**To the description.** The joint axes at ``q = 0`` give the description's Hayati-modified DH
parameters (frame ``i-1``'s z on joint ``i``'s axis, x along the common normal; axes within 1° of
parallel take Hayati's form, ``d = 0`` and the tilt in ``beta``); frame 0 is the base link, so joint 1's axis
must be its z axis; frame 6 is the tip link (any orientation when its origin is on joint 6's axis,
else its x axis must lie on the common normal). The description's FK is then checked against the
URDF's own at 64 poses and the file refused if they differ by more than 1e-6 mm or 1e-9 rad.
``theta_i = sign_i·A_i + offset_i`` with ``sign_i`` from the axis direction and the axis mapping,
``offset_i`` the DH angle at ``q = 0`` plus the mapping's offset. Limits are the URDF's ``lower``
/ ``upper`` in axis values (a continuous joint gets ±360°). Link ``i``'s mass and centre of mass
combine every link rigidly attached between joint ``i`` and joint ``i+1`` (the tip's side links
included). The tool is the tip link's origin unless the wrapper gives ``tool_xyz_mm``.

**To URDF** (:func:`format_urdf`): links ``base_link``, ``link_1`` … ``link_6``, ``tool0`` and
``tcp``; joint ``i``'s origin is ``Tz(d)·Tx(a)·Rx(alpha)·Ry(beta)`` of joint ``i-1`` (the base
frame for joint 1) followed by ``Rz(offset_i)``, its axis ``(0, 0, sign_i)``, so that the URDF
joint position is the controller's axis value in radians.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.files import read_text
from comp_daemon.robot.types import (
    N_JOINTS,
    Joint,
    RobotDescription,
    RobotDescriptionError,
    check_keys,
    number,
    vec3,
)

__all__ = [
    "CONTINUOUS_LIMIT_DEG",
    "UrdfChain",
    "UrdfJoint",
    "UrdfLink",
    "UrdfRobot",
    "description_from_urdf",
    "dh_transforms",
    "format_urdf",
    "load_urdf",
    "parse_urdf",
    "parse_urdf_wrapper",
    "rpy_of",
    "rpy_to_matrix",
]

FloatArray = NDArray[np.float64]

#: axis limits given to a continuous joint (deg)
CONTINUOUS_LIMIT_DEG = 360.0
#: largest FK difference between a URDF and the description made of it (mm, and rad for the frame)
MATCH_MM = 1e-6
MATCH_RAD = 1e-9
_TOL_MM = 1e-9  # below this, a length is zero (axes intersect, an origin is on an axis)
#: consecutive axes closer to parallel than this (deg) take Hayati's form (d = 0, beta)
HAYATI_BELOW_DEG = 1.0
_MOVING = ("revolute", "continuous")
_KNOWN_TYPES = ("revolute", "continuous", "fixed", "prismatic", "floating", "planar")


@dataclass(frozen=True, slots=True)
class UrdfLink:
    name: str
    mass_kg: float
    com_mm: tuple[float, float, float]  # in the link's frame


@dataclass(frozen=True, slots=True)
class UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    parent_T_joint: FloatArray  # (4, 4), mm
    axis: FloatArray  # (3,) unit, in the joint (child) frame
    lower_rad: float | None
    upper_rad: float | None


@dataclass(frozen=True, slots=True)
class UrdfRobot:
    name: str
    links: dict[str, UrdfLink]
    joints: tuple[UrdfJoint, ...]
    source: str

    def root(self) -> str:
        children = {j.child for j in self.joints}
        roots = [name for name in self.links if name not in children]
        if len(roots) != 1:
            raise RobotDescriptionError(
                f"{self.source}: {len(roots)} root links ({', '.join(roots)}); one expected"
            )
        return roots[0]


@dataclass(frozen=True, slots=True)
class UrdfChain:
    """The base → tip path: ``steps`` are fixed transforms (4×4, mm) and moving joints in order."""

    base_link: str
    tip_link: str
    steps: tuple[FloatArray | UrdfJoint, ...]
    moving: tuple[UrdfJoint, ...]
    # links rigid with each segment: [0] the base side, [i] the links moved by joint i alone
    segments: tuple[tuple[str, ...], ...] = field(default=())

    def fk(self, q_rad: FloatArray) -> FloatArray:
        """(n, 4, 4) tip link in the base link (mm) for joint positions (n, 6) in URDF radians."""
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        out = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        k = 0
        for step in self.steps:
            if isinstance(step, UrdfJoint):
                out = out @ step.parent_T_joint @ _rotation_about(step.axis, q[:, k])
                k += 1
            else:
                out = out @ step
        return out


# ------------------------------------------------------------------------------------ rotations
def rpy_to_matrix(rpy: Sequence[float]) -> FloatArray:
    """URDF's fixed-axis roll, pitch, yaw: ``Rz(yaw)·Ry(pitch)·Rx(roll)``."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_of(rot: FloatArray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of a rotation matrix (inverse of :func:`rpy_to_matrix`)."""
    pitch = math.atan2(-rot[2, 0], math.hypot(rot[0, 0], rot[1, 0]))
    if math.hypot(rot[0, 0], rot[1, 0]) < 1e-12:  # gimbal lock: yaw 0, all turn in roll
        return math.atan2(-rot[1, 2], rot[1, 1]), pitch, 0.0
    return math.atan2(rot[2, 1], rot[2, 2]), pitch, math.atan2(rot[1, 0], rot[0, 0])


def _rotation_about(axis: FloatArray, angle: FloatArray) -> FloatArray:
    """(n, 4, 4) rotations by ``angle`` (n,) about the unit ``axis`` (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    out = np.broadcast_to(np.eye(4), (len(angle), 4, 4)).copy()
    out[:, :3, :3] = np.eye(3) + s * k + (1.0 - c) * (k @ k)
    return out


def _transform(xyz_mm: Sequence[float] | FloatArray, rot: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = xyz_mm
    return out


def _inverse(t: FloatArray) -> FloatArray:
    return _transform(-t[:3, :3].T @ t[:3, 3], t[:3, :3].T)


def dh_transforms(table: FloatArray, theta_rad: FloatArray) -> FloatArray:
    """(n, 6, 4, 4) ``Rz(theta)·Tz(d)·Tx(a)·Rx(alpha)·Ry(beta)`` per joint; ``table`` rows are
    ``d, a, alpha, beta`` (mm, rad), ``theta_rad`` (n, 6)."""
    theta = np.atleast_2d(theta_rad)
    n = len(theta)
    d, a, alpha, beta = (np.broadcast_to(table[:, k], (n, N_JOINTS)) for k in range(4))
    ct, st, ca, sa, cb, sb = (
        np.cos(theta),
        np.sin(theta),
        np.cos(alpha),
        np.sin(alpha),
        np.cos(beta),
        np.sin(beta),
    )
    out = np.zeros((n, N_JOINTS, 4, 4))
    # Rz(t)·Rx(a)·Ry(b), written out
    out[..., 0, 0] = ct * cb - st * sa * sb
    out[..., 0, 1] = -st * ca
    out[..., 0, 2] = ct * sb + st * sa * cb
    out[..., 1, 0] = st * cb + ct * sa * sb
    out[..., 1, 1] = ct * ca
    out[..., 1, 2] = st * sb - ct * sa * cb
    out[..., 2, 0] = -ca * sb
    out[..., 2, 1] = sa
    out[..., 2, 2] = ca * cb
    out[..., 0, 3] = a * ct
    out[..., 1, 3] = a * st
    out[..., 2, 3] = d
    out[..., 3, 3] = 1.0
    return out


# ---------------------------------------------------------------------------------------- parse
def _floats(text: str | None, count: int, where: str, default: Sequence[float]) -> list[float]:
    if text is None:
        return list(default)
    parts = text.split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise RobotDescriptionError(f"{where}: expected {count} numbers, got {text!r}") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise RobotDescriptionError(f"{where}: expected {count} finite numbers, got {text!r}")
    return values


def _origin_mm(element: ET.Element | None, where: str) -> FloatArray:
    if element is None:
        return np.eye(4)
    xyz = _floats(element.get("xyz"), 3, f"{where} <origin xyz>", (0.0, 0.0, 0.0))
    rpy = _floats(element.get("rpy"), 3, f"{where} <origin rpy>", (0.0, 0.0, 0.0))
    return _transform([1000.0 * v for v in xyz], rpy_to_matrix(rpy))


def _link(element: ET.Element, source: str) -> UrdfLink:
    name = element.get("name")
    if not name:
        raise RobotDescriptionError(f"{source}: a <link> without a name")
    inertial = element.find("inertial")
    if inertial is None:
        return UrdfLink(name, 0.0, (0.0, 0.0, 0.0))
    where = f"{source} link '{name}' <inertial>"
    mass_el = inertial.find("mass")
    mass = 0.0 if mass_el is None else _floats(mass_el.get("value"), 1, f"{where} <mass value>", ())[0]
    if mass < 0:
        raise RobotDescriptionError(f"{where} <mass value>: must be >= 0, got {mass}")
    com = _origin_mm(inertial.find("origin"), where)[:3, 3]
    return UrdfLink(name, mass, (float(com[0]), float(com[1]), float(com[2])))


def _joint(element: ET.Element, source: str) -> UrdfJoint:
    name = element.get("name") or "?"
    where = f"{source} joint '{name}'"
    jtype = element.get("type")
    if jtype not in _KNOWN_TYPES:
        raise RobotDescriptionError(
            f"{where}: type {jtype!r} is not a URDF joint type ({', '.join(_KNOWN_TYPES)})"
        )
    parent, child = element.find("parent"), element.find("child")
    if parent is None or not parent.get("link") or child is None or not child.get("link"):
        raise RobotDescriptionError(f"{where}: needs <parent link=…> and <child link=…>")
    axis_el = element.find("axis")
    axis = np.array(
        _floats(None if axis_el is None else axis_el.get("xyz"), 3, f"{where} <axis xyz>", (1, 0, 0))
    )
    if jtype in _MOVING and np.linalg.norm(axis) < 1e-9:
        raise RobotDescriptionError(f"{where} <axis xyz>: a zero axis")
    lower = upper = None
    limit = element.find("limit")
    if jtype == "revolute":
        if limit is None or limit.get("lower") is None or limit.get("upper") is None:
            raise RobotDescriptionError(f"{where}: a revolute joint needs <limit lower=… upper=…>")
        lower = _floats(limit.get("lower"), 1, f"{where} <limit lower>", ())[0]
        upper = _floats(limit.get("upper"), 1, f"{where} <limit upper>", ())[0]
        if lower >= upper:
            raise RobotDescriptionError(f"{where} <limit>: lower ({lower}) must be below upper ({upper})")
    return UrdfJoint(
        name=name,
        type=jtype,
        parent=str(parent.get("link")),
        child=str(child.get("link")),
        parent_T_joint=_origin_mm(element.find("origin"), where),
        axis=axis / max(float(np.linalg.norm(axis)), 1e-300),
        lower_rad=lower,
        upper_rad=upper,
    )


def parse_urdf(text: str, source: str = "<urdf>") -> UrdfRobot:
    """The links and joints of a URDF document (refused, naming the element, when malformed)."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise RobotDescriptionError(f"{source}: not valid XML: {exc}") from None
    if root.tag != "robot":
        raise RobotDescriptionError(f"{source}: the root element is <{root.tag}>, not <robot>")
    if root.find(".//{http://www.ros.org/wiki/xacro}macro") is not None or "xacro:" in text:
        raise RobotDescriptionError(
            f"{source}: a xacro file; expand it first (xacro FILE.urdf.xacro > FILE.urdf)"
        )
    links: dict[str, UrdfLink] = {}
    for element in root.findall("link"):
        link = _link(element, source)
        if link.name in links:
            raise RobotDescriptionError(f"{source}: link '{link.name}' is defined twice")
        links[link.name] = link
    joints = tuple(_joint(element, source) for element in root.findall("joint"))
    seen: set[str] = set()
    for joint in joints:
        for end in (joint.parent, joint.child):
            if end not in links:
                raise RobotDescriptionError(f"{source} joint '{joint.name}': link '{end}' is not defined")
        if joint.child in seen:
            raise RobotDescriptionError(f"{source}: link '{joint.child}' is the child of two joints")
        seen.add(joint.child)
    return UrdfRobot(str(root.get("name") or "URDF robot"), links, joints, source)


# ---------------------------------------------------------------------------------------- chain
def _path_up(robot: UrdfRobot, link: str) -> list[UrdfJoint]:
    """The joints from ``link`` up to the root, nearest first."""
    by_child = {j.child: j for j in robot.joints}
    out = []
    while link in by_child:
        out.append(by_child[link])
        link = by_child[link].parent
    return out


def _default_tip(robot: UrdfRobot, base: str) -> str:
    if "tool0" in robot.links:
        return "tool0"
    parents = {j.parent for j in robot.joints}
    below = {base}
    changed = True
    while changed:
        changed = False
        for j in robot.joints:
            if j.parent in below and j.child not in below:
                below.add(j.child)
                changed = True
    leaves = sorted(n for n in below if n not in parents)
    if len(leaves) == 1:
        return leaves[0]
    # the leaves six moving joints below the base
    deep = [leaf for leaf in leaves if sum(j.type in _MOVING for j in _path_up(robot, leaf)) >= N_JOINTS]
    if len(deep) != 1:
        raise RobotDescriptionError(
            f"{robot.source}: no 'tool0' link and {len(deep)} candidate tip links "
            f"({', '.join(deep) or 'none'}); name one as tip_link in a [urdf] wrapper"
        )
    return deep[0]


def urdf_chain(robot: UrdfRobot, base_link: str | None = None, tip_link: str | None = None) -> UrdfChain:
    """The path from ``base_link`` to ``tip_link`` (defaults in the module docstring)."""
    base = base_link or robot.root()
    for role, name in (("base_link", base), ("tip_link", tip_link)):
        if name is not None and name not in robot.links:
            raise RobotDescriptionError(f"{robot.source}: {role} '{name}' is not a link of this URDF")
    tip = tip_link or _default_tip(robot, base)
    up_base, up_tip = _path_up(robot, base), _path_up(robot, tip)
    tip_names = [tip, *(j.parent for j in up_tip)]
    base_names = [base, *(j.parent for j in up_base)]
    common = next(n for n in base_names if n in tip_names)
    rise = up_base[: base_names.index(common)]
    fall = list(reversed(up_tip[: tip_names.index(common)]))
    for joint in rise:
        if joint.type != "fixed":
            raise RobotDescriptionError(
                f"{robot.source}: joint '{joint.name}' ({joint.type}) lies between base_link '{base}' "
                f"and the chain to '{tip}'; the base must not move"
            )
    steps: list[FloatArray | UrdfJoint] = [_inverse(j.parent_T_joint) for j in rise]
    moving: list[UrdfJoint] = []
    for joint in fall:
        if joint.type == "fixed":
            steps.append(joint.parent_T_joint)
        elif joint.type in _MOVING:
            steps.append(joint)
            moving.append(joint)
        else:
            raise RobotDescriptionError(
                f"{robot.source}: joint '{joint.name}' is {joint.type}; only revolute, continuous and "
                "fixed joints are read"
            )
    if len(moving) != N_JOINTS:
        raise RobotDescriptionError(
            f"{robot.source}: {len(moving)} revolute joints from '{base}' to '{tip}' "
            f"({', '.join(j.name for j in moving) or 'none'}); six are expected"
        )
    # links rigid with each segment, for the masses
    segments: list[list[str]] = [[]]
    owner: dict[str, int] = {base: 0, **{n: 0 for n in base_names}}
    for joint in fall:
        owner[joint.child] = owner[joint.parent] + (joint.type in _MOVING)
    changed = True
    while changed:  # side links hanging on fixed joints
        changed = False
        for joint in robot.joints:
            if joint.type == "fixed" and joint.parent in owner and joint.child not in owner:
                owner[joint.child] = owner[joint.parent]
                changed = True
    segments = [[n for n, k in owner.items() if k == i] for i in range(N_JOINTS + 1)]
    return UrdfChain(base, tip, tuple(steps), tuple(moving), tuple(tuple(s) for s in segments))


# -------------------------------------------------------------------------- URDF → description
def _link_frames_at_zero(robot: UrdfRobot, chain: UrdfChain) -> dict[str, FloatArray]:
    """Every link of the chain's segments in the base link at q = 0 (mm)."""
    frames: dict[str, FloatArray] = {chain.base_link: np.eye(4)}
    by_child = {j.child: j for j in robot.joints}
    by_parent: dict[str, list[UrdfJoint]] = {}
    for j in robot.joints:
        by_parent.setdefault(j.parent, []).append(j)
    todo = [chain.base_link]
    while todo:  # walk down from the base, and up through fixed joints
        link = todo.pop()
        for j in by_parent.get(link, []):
            if j.child not in frames:
                frames[j.child] = frames[link] @ j.parent_T_joint
                todo.append(j.child)
        up = by_child.get(link)
        if up is not None and up.type == "fixed" and up.parent not in frames:
            frames[up.parent] = frames[link] @ _inverse(up.parent_T_joint)
            todo.append(up.parent)
    return frames


def _segment(
    o_prev: FloatArray, x_prev: FloatArray, z_prev: FloatArray, p: FloatArray, z: FloatArray, where: str
) -> tuple[list[float], FloatArray, FloatArray]:
    """The DH row (theta at q = 0, d, a, alpha, beta) from the frame (o_prev, x_prev, z_prev) to the
    next one on the axis line (p, z), and that frame's origin and x axis."""
    w = p - o_prev
    cos_angle = float(z_prev @ z)
    if abs(cos_angle) < math.cos(math.radians(HAYATI_BELOW_DEG)):
        # common normal between the lines: closest points o_prev + t·z_prev and p + s·z
        n = np.cross(z_prev, z)
        denom = 1.0 - cos_angle * cos_angle
        t = (float(w @ z_prev) - cos_angle * float(w @ z)) / denom
        s = (cos_angle * float(w @ z_prev) - float(w @ z)) / denom
        foot_a, foot_b = o_prev + t * z_prev, p + s * z
        gap = foot_b - foot_a
        a = float(np.linalg.norm(gap))
        x = gap / a if a > _TOL_MM else n / np.linalg.norm(n)
        row = [_angle(x_prev, x, z_prev), t, a if a > _TOL_MM else 0.0, _angle(z_prev, z, x), 0.0]
        return row, foot_b, x
    # (nearly) parallel: Hayati's form, d = 0, the origin where the axis meets the plane through
    # o_prev normal to z_prev
    origin = p - (float(w @ z_prev) / cos_angle) * z
    gap = origin - o_prev
    a = float(np.linalg.norm(gap))
    if a <= _TOL_MM:
        raise RobotDescriptionError(f"{where}: its axis coincides with the previous joint's")
    x1 = gap / a
    y1 = np.cross(z_prev, x1)
    zx, zy, zz = float(z @ x1), float(z @ y1), float(z @ z_prev)
    alpha, beta = math.atan2(-zy, zz), math.atan2(zx, math.hypot(zy, zz))
    sa, ca, sb, cb = math.sin(alpha), math.cos(alpha), math.sin(beta), math.cos(beta)
    x = cb * x1 + sa * sb * y1 - ca * sb * z_prev
    return [_angle(x_prev, x1, z_prev), 0.0, a, alpha, beta], origin, x


def _angle(u: FloatArray, v: FloatArray, about: FloatArray) -> float:
    return math.atan2(float(np.cross(u, v) @ about), float(u @ v))


def _frame_of(origin: FloatArray, x: FloatArray, z: FloatArray) -> FloatArray:
    return _transform(origin, np.column_stack([x, np.cross(z, x), z]))


def _last_segment(five_T_tip: FloatArray, where: str) -> tuple[float, float, float, float, float]:
    """theta, d, a, alpha, beta with Rz(theta)·Tz(d)·Tx(a)·Rx(alpha)·Ry(beta) = five_T_tip."""
    px, py, pz = five_T_tip[:3, 3]
    rot = five_T_tip[:3, :3]
    a = math.hypot(px, py)
    if a > _TOL_MM:
        theta = math.atan2(py, px)
        c, s = math.cos(theta), math.sin(theta)
        rest = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ rot  # Rx(alpha)·Ry(beta)
        if abs(rest[0, 1]) > 1e-12:
            raise RobotDescriptionError(
                f"{where}: the tip link's x axis is not on the normal from joint 6's axis to its origin; "
                "the description cannot hold this frame (choose another tip_link)"
            )
        return theta, float(pz), a, math.atan2(rest[2, 1], rest[1, 1]), math.atan2(rest[0, 2], rest[0, 0])
    # origin on the axis: Rz(theta)·Rx(alpha)·Ry(beta) is any rotation
    alpha = math.atan2(rot[2, 1], math.hypot(rot[0, 1], rot[1, 1]))
    theta = math.atan2(-rot[0, 1], rot[1, 1])
    beta = math.atan2(-rot[2, 0], rot[2, 2])
    return theta, float(pz), 0.0, alpha, beta


@dataclass(frozen=True, slots=True)
class AxisMapping:
    """``q_urdf_i = radians(sign_i · A_i + offset_deg_i)`` (module docstring)."""

    sign: tuple[int, ...] = (1,) * N_JOINTS
    offset_deg: tuple[float, ...] = (0.0,) * N_JOINTS


def description_from_urdf(
    robot: UrdfRobot,
    base_link: str | None = None,
    tip_link: str | None = None,
    mapping: AxisMapping | None = None,
    repeatability_mm: float | None = None,
    tool_xyz_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
    name: str | None = None,
) -> RobotDescription:
    """The description of a URDF's chain (module docstring); checked against the URDF's own FK."""
    mapping = mapping or AxisMapping()
    chain = urdf_chain(robot, base_link, tip_link)
    frames = _link_frames_at_zero(robot, chain)
    src = robot.source
    lines = []
    for joint in chain.moving:
        at = frames[joint.child]  # the joint frame is the child link's frame at q = 0
        lines.append((at[:3, 3].copy(), at[:3, :3] @ joint.axis))
    p1, u1 = lines[0]
    first = f"{src} joint '{chain.moving[0].name}'"
    if np.linalg.norm(np.cross(u1, [0.0, 0.0, 1.0])) > 1e-9 or math.hypot(p1[0], p1[1]) > 1e-6:
        raise RobotDescriptionError(
            f"{first}: its axis is not the z axis of base_link '{chain.base_link}' "
            f"(axis {np.round(u1, 9).tolist()} through {np.round(p1, 6).tolist()} mm); the description's "
            "base frame must be (choose another base_link)"
        )
    dh_sign = [1.0 if u1[2] > 0 else -1.0] + [1.0] * (N_JOINTS - 1)
    z_axes = [np.array([0.0, 0.0, 1.0])] + [u for _, u in lines[1:]]
    origin, x_prev = np.zeros(3), np.array([1.0, 0.0, 0.0])
    table = np.zeros((N_JOINTS, 5))  # theta0, d, a, alpha, beta
    for i in range(N_JOINTS - 1):
        where = f"{src} joint '{chain.moving[i + 1].name}'"
        table[i], origin, x_prev = _segment(origin, x_prev, z_axes[i], lines[i + 1][0], z_axes[i + 1], where)
    five = _frame_of(origin, x_prev, z_axes[-1])
    table[-1] = _last_segment(_inverse(five) @ frames[chain.tip_link], f"{src} tip link '{chain.tip_link}'")

    masses, coms = _segment_masses(robot, chain, frames, table)
    joints = []
    for i, joint in enumerate(chain.moving):
        s_map, o_map = mapping.sign[i], mapping.offset_deg[i]
        sign = int(dh_sign[i] * s_map)
        if joint.lower_rad is None or joint.upper_rad is None:
            lo, hi = -CONTINUOUS_LIMIT_DEG, CONTINUOUS_LIMIT_DEG
        else:  # q = s·A + o  ->  A = (q - o)·s
            ends = sorted((math.degrees(v) - o_map) * s_map for v in (joint.lower_rad, joint.upper_rad))
            lo, hi = ends
        joints.append(
            Joint(
                a_mm=_clean(table[i, 2]),
                alpha_deg=_clean(math.degrees(table[i, 3])),
                d_mm=_clean(table[i, 1]),
                beta_deg=_clean(math.degrees(table[i, 4])),
                sign=sign,
                offset_deg=_wrap_deg(math.degrees(table[i, 0]) + dh_sign[i] * o_map),
                min_deg=lo,
                max_deg=hi,
                mass_kg=masses[i],
                com_mm=coms[i],
            )
        )
    out = RobotDescription(
        name=name or robot.name,
        repeatability_mm=repeatability_mm if repeatability_mm is not None else UNSTATED_REPEATABILITY_MM,
        tool_xyz_mm=tool_xyz_mm,
        joints=tuple(joints),
        source=src,
    )
    _check_against_urdf(out, chain, mapping)
    return out


#: the repeatability given to a URDF robot whose wrapper does not state one (a URDF has no such
#: field; only the simulated cell's reports use it)
UNSTATED_REPEATABILITY_MM = 0.1


def _clean(value: float) -> float:
    return float(value) + 0.0  # no "-0.0"


def _wrap_deg(angle: float) -> float:
    out = (angle + 180.0) % 360.0 - 180.0
    return 0.0 if abs(out) < 1e-12 else out


def _segment_masses(
    robot: UrdfRobot, chain: UrdfChain, frames: dict[str, FloatArray], table: FloatArray
) -> tuple[list[float], list[tuple[float, float, float]]]:
    """Mass and centre of mass (in DH frame i) of the links moved by joint i and not by joint i+1."""
    theta = table[:, 0][None, :]
    dh = dh_transforms(table[:, 1:], theta)[0]
    base_T_dh = np.eye(4)
    masses, coms = [], []
    for i in range(N_JOINTS):
        base_T_dh = base_T_dh @ dh[i]
        total, moment = 0.0, np.zeros(3)
        for name in chain.segments[i + 1]:
            link = robot.links[name]
            if link.mass_kg > 0:
                total += link.mass_kg
                moment += link.mass_kg * (frames[name] @ np.array([*link.com_mm, 1.0]))[:3]
        com = (_inverse(base_T_dh) @ np.array([*(moment / total if total > 0 else base_T_dh[:3, 3]), 1.0]))[
            :3
        ]
        masses.append(total)
        coms.append((float(com[0]), float(com[1]), float(com[2])) if total > 0 else (0.0, 0.0, 0.0))
    return masses, coms


def description_fk(robot: RobotDescription, a_deg: FloatArray) -> FloatArray:
    """(n, 4, 4) flange (frame 6) in the base frame for axis values (n, 6) in deg."""
    table = np.array(
        [[j.d_mm, j.a_mm, math.radians(j.alpha_deg), math.radians(j.beta_deg)] for j in robot.joints]
    )
    theta = np.radians(np.asarray(a_deg, dtype=float) * robot.sign + robot.offset_deg)
    dh = dh_transforms(table, theta)
    out = dh[:, 0]
    for i in range(1, N_JOINTS):
        out = out @ dh[:, i]
    return out


def _check_against_urdf(desc: RobotDescription, chain: UrdfChain, mapping: AxisMapping) -> None:
    rng = np.random.default_rng(0)
    limits = desc.axis_limits_deg
    a_deg = rng.uniform(limits[:, 0], limits[:, 1], size=(64, N_JOINTS))
    q = np.radians(a_deg * np.array(mapping.sign) + np.array(mapping.offset_deg))
    want, got = chain.fk(q), description_fk(desc, a_deg)
    dp = float(np.max(np.abs(want[:, :3, 3] - got[:, :3, 3])))
    dr = float(np.max(np.abs(want[:, :3, :3] - got[:, :3, :3])))
    if dp > MATCH_MM or dr > MATCH_RAD:
        raise RobotDescriptionError(
            f"{desc.source}: the description made of this URDF differs from its own forward kinematics "
            f"by {dp:.3g} mm / {dr:.3g} rad; not used"
        )


# ------------------------------------------------------------------------------- wrapper, load
_WRAPPER_KEYS = {
    "file": "",
    "name": "",
    "base_link": "",
    "tip_link": "",
    "axis_sign": "",
    "axis_offset_deg": "deg",
    "repeatability_mm": "mm",
    "tool_xyz_mm": "mm",
}


def load_urdf(path: Path, source: str | None = None, **options: Any) -> RobotDescription:
    """The description of the URDF file at ``path`` (options of :func:`description_from_urdf`)."""
    text = read_text(path, RobotDescriptionError)
    return description_from_urdf(parse_urdf(text, source or str(path)), **options)


def _six(value: Any, where: str) -> list[float]:
    if not isinstance(value, list) or len(value) != N_JOINTS:
        raise RobotDescriptionError(f"{where}: expected a list of six numbers, got {value!r}")
    return [number(v, f"{where}[{k}]") for k, v in enumerate(value)]


def parse_urdf_wrapper(doc: dict[str, Any], source: str, directory: Path) -> RobotDescription:
    """A robot description TOML holding a ``[urdf]`` table: the URDF ``file`` (relative to the
    TOML's directory) and, optionally, ``name``, ``base_link``, ``tip_link``, ``axis_sign`` and
    ``axis_offset_deg`` (six each: ``q_urdf = radians(sign·A + offset)``), ``repeatability_mm``,
    ``tool_xyz_mm``."""
    check_keys(doc, {"urdf": ""}, source)
    table = doc["urdf"]
    where = f"{source} [urdf]"
    if not isinstance(table, dict):
        raise RobotDescriptionError(f"{where}: must be a table")
    check_keys(table, _WRAPPER_KEYS, where)
    file = table.get("file")
    if not isinstance(file, str) or not file:
        raise RobotDescriptionError(f"{where}: missing field 'file' (the URDF's path)")
    for key in ("name", "base_link", "tip_link"):
        if key in table and not (isinstance(table[key], str) and table[key].strip()):
            raise RobotDescriptionError(f"{where}.{key}: expected a non-empty string, got {table[key]!r}")
    signs = _six(table.get("axis_sign", [1] * N_JOINTS), f"{where}.axis_sign")
    if any(s not in (1.0, -1.0) for s in signs):
        raise RobotDescriptionError(f"{where}.axis_sign: each must be 1 or -1, got {table['axis_sign']!r}")
    offsets = _six(table.get("axis_offset_deg", [0.0] * N_JOINTS), f"{where}.axis_offset_deg")
    repeatability = None
    if "repeatability_mm" in table:
        repeatability = number(table["repeatability_mm"], f"{where}.repeatability_mm")
        if repeatability <= 0:
            raise RobotDescriptionError(f"{where}.repeatability_mm: must be > 0, got {repeatability}")
    tool = vec3(table.get("tool_xyz_mm", [0.0, 0.0, 0.0]), f"{where}.tool_xyz_mm")
    path = Path(file) if Path(file).is_absolute() else directory / file
    if not path.is_file():
        raise RobotDescriptionError(f"{where}.file: '{path}' is not a readable file")
    return load_urdf(
        path,
        source=source,
        base_link=table.get("base_link"),
        tip_link=table.get("tip_link"),
        mapping=AxisMapping(tuple(int(s) for s in signs), tuple(offsets)),
        repeatability_mm=repeatability,
        tool_xyz_mm=tool,
        name=table.get("name"),
    )


# ---------------------------------------------------------------------------------- write URDF
def _num(value: float) -> str:
    """The shortest text that reads back to the same double (``repr``; no ``-0``)."""
    return repr(float(value) + 0.0)


def _origin_xml(t: FloatArray) -> str:
    xyz = " ".join(_num(v / 1000.0) for v in t[:3, 3])
    rpy = " ".join(_num(v) for v in rpy_of(t[:3, :3]))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def format_urdf(
    name: str,
    table: FloatArray,
    sign: FloatArray,
    limits_deg: FloatArray,
    base_T_root: FloatArray,
    tool_xyz_mm: FloatArray,
    masses_kg: FloatArray,
    coms_mm: FloatArray,
    comments: Sequence[str] = (),
) -> str:
    """URDF text of a kinematic chain: ``table`` (6, 5) rows ``theta_offset, d, a, alpha, beta``
    (rad, mm), ``sign`` (6,), axis limits (6, 2) deg, ``base_T_root`` (4, 4) mm, the TCP in the
    flange (mm), link masses (6,) and centres of mass (6, 3) in DH frame i (module docstring).

    The joints' ``effort`` and ``velocity`` limits are not known here and written as 0; copy
    them from the robot maker's URDF."""
    offsets, seg = table[:, 0], table[:, 1:]
    after = dh_transforms(seg, np.zeros((1, N_JOINTS)))[0]  # Tz(d)·Tx(a)·Rx(alpha)·Ry(beta)
    lines = ['<?xml version="1.0"?>']
    lines += [f"<!-- {c.replace('--', '- -')} -->" for c in comments]
    lines.append(f'<robot name="{_xml_attr(name)}">')
    lines.append('  <link name="base_link"/>')
    for i in range(N_JOINTS):
        link = f"link_{i + 1}"
        com = after[i] @ np.array([*coms_mm[i], 1.0])
        if masses_kg[i] > 0:
            com_xyz = " ".join(_num(v / 1000.0) for v in com[:3])
            lines += [
                f'  <link name="{link}">',
                f'    <inertial><origin xyz="{com_xyz}" rpy="0 0 0"/><mass value="{_num(masses_kg[i])}"/>'
                '<inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial>',
                "  </link>",
            ]
        else:
            lines.append(f'  <link name="{link}"/>')
    lines += ['  <link name="tool0"/>', '  <link name="tcp"/>']
    rz = [
        _transform(
            (0, 0, 0), np.array([[math.cos(o), -math.sin(o), 0], [math.sin(o), math.cos(o), 0], [0, 0, 1]])
        )
        for o in offsets
    ]
    for i in range(N_JOINTS):
        parent = "base_link" if i == 0 else f"link_{i}"
        before = base_T_root if i == 0 else after[i - 1]
        lo, hi = np.radians(limits_deg[i])
        lines += [
            f'  <joint name="joint_{i + 1}" type="revolute">',
            f'    <parent link="{parent}"/><child link="link_{i + 1}"/>',
            f"    {_origin_xml(before @ rz[i])}",
            f'    <axis xyz="0 0 {int(sign[i])}"/>',
            f'    <limit lower="{_num(lo)}" upper="{_num(hi)}" effort="0" velocity="0"/>',
            "  </joint>",
        ]
    lines += [
        '  <joint name="joint_6-tool0" type="fixed">',
        f'    <parent link="link_6"/><child link="tool0"/>{_origin_xml(after[-1])}',
        "  </joint>",
        '  <joint name="tool0-tcp" type="fixed">',
        f'    <parent link="tool0"/><child link="tcp"/>{_origin_xml(_transform(tool_xyz_mm, np.eye(3)))}',
        "  </joint>",
        "</robot>",
    ]
    return "\n".join(lines) + "\n"


def _xml_attr(text: str) -> str:
    return text.replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;").replace(">", "&gt;")


def description_urdf(robot: RobotDescription, comments: Sequence[str] = ()) -> str:
    """URDF text of a description's nominal kinematics (base frame = chain root)."""
    table = np.array(
        [
            [math.radians(j.offset_deg), j.d_mm, j.a_mm, math.radians(j.alpha_deg), math.radians(j.beta_deg)]
            for j in robot.joints
        ]
    )
    return format_urdf(
        robot.name,
        table,
        robot.sign,
        robot.axis_limits_deg,
        np.eye(4),
        np.array(robot.tool_xyz_mm),
        robot.link_mass_kg,
        robot.link_com_mm,
        comments,
    )
