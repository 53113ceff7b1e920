"""A kinematic model's calibrated geometry as a URDF (``export params --format urdf``).

The URDF is the robot's chain in the robot base frame: the model's identified joint table, its
``base`` (the chain's root in the robot base frame) as joint 1's origin, its tool as a fixed
``tcp`` link below ``tool0`` (the flange, z out of it); the layout and the joint convention are
:func:`comp_daemon.robot.urdf.format_urdf`'s (a URDF joint position is the controller's axis value
in radians). The registration (the robot base in the tracker's frame) is not part of the robot
and not written; nor are non-geometric effects (backlash, ratio errors, compliance …), which a
URDF cannot hold: the header comment names those left out. Link masses and centres of mass are
the robot description's; inertia tensors and the joints' effort and velocity limits are not known
to comp-daemon and written as zero.

:func:`urdf_text` reads its own text back (:func:`comp_daemon.robot.urdf.parse_urdf`) and refuses
it unless the URDF's FK puts the TCP where the model's geometry does, to 1e-6 mm, at the corners
and the middle of the axis ranges and at 64 random poses.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from comp_daemon.export.frames import rigid_inverse
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.robot.urdf import format_urdf, parse_urdf, urdf_chain

__all__ = ["ROUND_TRIP_MM", "geometry_tcp_mm", "urdf_text"]

#: the largest TCP difference (mm) a URDF read back may make
ROUND_TRIP_MM = 1e-6


def geometry_tcp_mm(model: KinematicModel, a_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3) the TCP of the model's geometry alone (no effects) in the robot base frame."""
    geometric = KinematicModel(model.robot, model.params, None, model.registration)
    return _apply(rigid_inverse(np.asarray(model.registration, dtype=float)), geometric.predict_tcp_mm(a_deg))


def _apply(t: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    return p @ t[:3, :3].T + t[:3, 3]


def _probe_poses(limits_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    rng = np.random.default_rng(0)
    corners = np.concatenate([limits_deg.T, limits_deg.mean(axis=1)[None, :]])
    return np.concatenate([corners, rng.uniform(limits_deg[:, 0], limits_deg[:, 1], size=(64, 6))])


def urdf_text(model: KinematicModel, header: Sequence[str] = ()) -> tuple[str, float]:
    """The URDF of ``model``'s calibrated geometry and the largest TCP difference (mm) of the URDF
    read back from the model; ValueError when that exceeds :data:`ROUND_TRIP_MM`."""
    params, robot = model.params, model.robot
    reg = np.asarray(model.registration, dtype=float)
    left_out = []
    if model.effects is not None:
        names = [
            n
            for n, v in zip(model.effects.names(), model.effects.get(model.effects.names()), strict=True)
            if v
        ]
        if names:
            left_out.append(
                "not in this URDF (a URDF cannot hold them): the model's non-geometric effects "
                + ", ".join(names)
            )
    comments = [
        *header,
        "geometry: comp-daemon's Hayati-modified DH (Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)); "
        "joint i's position is the controller's axis value Ai in rad",
        "frames: base_link is the robot base frame, tool0 the flange (z out of it), tcp the model's TCP",
        "inertia tensors, effort and velocity limits: not known to comp-daemon, written as 0",
        *left_out,
    ]
    text = format_urdf(
        robot.name,
        params.joint_table(),
        params.sign,
        robot.axis_limits_deg,
        rigid_inverse(reg) @ params.world_T_base,
        params.tool_xyz_mm,
        robot.link_mass_kg,
        robot.link_com_mm,
        comments,
    )
    chain = urdf_chain(parse_urdf(text, "<urdf export>"), "base_link", "tcp")
    a_deg = _probe_poses(robot.axis_limits_deg)
    back = chain.fk(np.radians(a_deg))[:, :3, 3]
    diff = float(np.max(np.abs(back - geometry_tcp_mm(model, a_deg))))
    if diff > ROUND_TRIP_MM:
        raise ValueError(f"the URDF read back moves the TCP by {diff:.3g} mm")
    return text, diff
