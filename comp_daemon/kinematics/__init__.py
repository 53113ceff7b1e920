"""Kinematics of six-axis arms: parameters, batch forward kinematics, Jacobians, gravity, inverse kinematics.

Conventions are in :mod:`comp_daemon.kinematics.params`; everything is batch-first over n poses.
"""

from comp_daemon.kinematics.forward import (
    chain,
    flange_pose,
    geometric_jacobian,
    gravity_torques_nm,
    identification_jacobian,
    position_jacobian_mm,
    tcp_position_mm,
)
from comp_daemon.kinematics.inverse import IKResult, UnreachableTargetError, require_reachable, solve_ik
from comp_daemon.kinematics.params import (
    N_PARAMS,
    PARAM_NAMES,
    KinematicParams,
    axes_deg_to_q_rad,
    q_rad_to_axes_deg,
)

__all__ = [
    "N_PARAMS",
    "PARAM_NAMES",
    "IKResult",
    "KinematicParams",
    "UnreachableTargetError",
    "axes_deg_to_q_rad",
    "chain",
    "flange_pose",
    "geometric_jacobian",
    "gravity_torques_nm",
    "identification_jacobian",
    "position_jacobian_mm",
    "q_rad_to_axes_deg",
    "require_reachable",
    "solve_ik",
    "tcp_position_mm",
]
