"""Whether a campaign's measured positions can be millimetres of its robot: the one rule.

``data check``, ``fit`` (every model kind) and ``diagnose`` all ask :func:`millimetre_problem`, so a
file that one of them refuses for its units is refused by the others with the same sentence. The
test itself (the spread of the measured points against the nominal TCP's at the same axis values)
is :func:`comp_daemon.estimation.registration.scale_problem`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.registration import scale_problem
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import RobotDescription

__all__ = ["millimetre_problem"]


def millimetre_problem(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    xyz_mm: NDArray[np.float64],
    station: Sequence[str] | None = None,
) -> str | None:
    """A sentence when the measured ``xyz_mm`` (n, 3) at axis values ``a_deg`` (n, 6) cannot be
    millimetres of ``robot`` (metres, centimetres, inches …), else None. With ``station`` (n,),
    each station's rows are judged apart (each is in its own frame; the sentence names it)."""
    nominal = KinematicParams.from_robot(robot)
    p_nominal_mm = tcp_position_mm(nominal, axes_deg_to_q_rad(np.asarray(a_deg, dtype=float), nominal.sign))
    p = np.asarray(xyz_mm, dtype=float)
    if station is None or len(set(station)) < 2:
        return scale_problem(p_nominal_mm, p)
    names = np.asarray(station, dtype=str)
    for name in sorted(set(station)):
        rows = names == name
        problem = scale_problem(p_nominal_mm[rows], p[rows])
        if problem is not None:
            return f"station {name}: {problem}"
    return None
