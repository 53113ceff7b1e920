"""Where the cell is: the grating converters' ports and geometry, the motion port, the home pose.

On a line they come from the configuration (``[encoders]``, ``run --motion HOST:PORT``,
:func:`configured_ports`); with ``--sim`` from what the simulated cell reports when it is up
(:func:`comp_daemon.daemon.simcell.start_simulated_cell`). The real-time process opens the grating
ports, the executor and the grating calibration move the robot through the motion port.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from comp_daemon.daemon.gratings import GratingGeometry
from comp_daemon.daemon.motion import LineMotionPort
from comp_daemon.rt.executor import MotionPort
from comp_daemon.service.config import Settings

__all__ = ["CellPorts", "configured_ports"]


@dataclass(frozen=True, slots=True)
class CellPorts:
    """``gratings``: joint → (serial port, bits); ``geometry``: joint → radius and resolution;
    ``motion``: None when nothing can move the robot; ``home_deg``: where the robot rests, if known."""

    gratings: Mapping[int, tuple[str, int]] = field(default_factory=dict)
    geometry: Mapping[int, GratingGeometry] = field(default_factory=dict)
    motion: MotionPort | None = None
    home_deg: tuple[float, ...] | None = None


def configured_ports(settings: Settings, motion_address: tuple[str, int] | None) -> CellPorts:
    """The ports of a real cell: ``[encoders]`` and the motion gateway (if one is given)."""
    enc = settings.encoders
    motion = None
    if motion_address is not None:
        motion = LineMotionPort(*motion_address, timeout_s=settings.controller.move_timeout_s)
    return CellPorts(
        gratings={j.joint: (j.port, j.bits) for j in enc.joints},
        geometry={j.joint: GratingGeometry(j.radius_mm, j.resolution_nm) for j in enc.joints},
        motion=motion,
    )
