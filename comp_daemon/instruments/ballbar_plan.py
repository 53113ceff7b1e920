"""The ballbar measurement plan (seed 002, spec A.6): arcs, orientations, and how many arcs.

:func:`plan_arcs` is the list of arcs a plan takes, in order: the spec's three (ψ = 10° from φ −90°
to 90°; the x–z and the y–z great circles over the top) and, beyond three, further circles through
three points on the pivot sphere (:data:`EXTRA_ARC_POINTS`). :func:`ballbar_plan` turns the first
``k`` of them into axis values by the nominal inverse kinematics, the flange held at one orientation
per arc (:data:`ORIENTATIONS`: the paper's vertical tool, a tilted one, or a different one per arc,
which identifies the most, spec A.4).

How many arcs (spec A.6, Fig. 4): :func:`arc_count_rates` compares, for k = 2..4 arcs, the mean and
the variance of the error magnitude ‖ΔP‖ over the plan's points with those over random poses of the
measurement region (points of the pivot sphere above ψ = 5°, random orientation change within
``spread_deg``): change rate = |s_k − s_ref| / s_ref. :func:`variogram_table` is γ(h) of the same
error field over joint-space lags (the error is smooth: no nugget, quadratic at the origin), with
the arc's point step marked. The error field is a prior draw of the POE errors; by default the
spec's Table 5 draw.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.instruments.ballbar import (
    PAPER_PIVOT_MM,
    PAPER_RADIUS_MM,
    Arc,
    _error_field,
    arc_through_points,
    default_arcs,
    error_variogram,
    plan_ballbar_axes,
    sphere_point_mm,
)
from comp_daemon.kinematics.forward import flange_pose
from comp_daemon.kinematics.inverse import solve_ik_axes
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.poe import PoeModel
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "EXTRA_ARC_POINTS",
    "ORIENTATIONS",
    "TABLE5_ERRORS",
    "ArcCountRates",
    "BallbarPlan",
    "arc_count_rates",
    "ballbar_plan",
    "plan_arcs",
    "variogram_table",
]

Orientation = Literal["per-arc", "vertical", "tilted"]
# axis values (deg) whose nominal flange orientation each arc keeps (spec A.4's three cases)
_VERTICAL = (0.0, 0.0, 0.0, 0.0, 90.0, 0.0)
_TILTED = (0.0, 0.0, 0.0, 30.0, 60.0, 0.0)
_OTHER = (0.0, 0.0, 0.0, -30.0, 70.0, 20.0)
ORIENTATIONS: dict[str, tuple[tuple[float, ...], ...]] = {
    "per-arc": (_VERTICAL, _TILTED, _OTHER),
    "vertical": (_VERTICAL,),
    "tilted": (_TILTED,),
}
# arcs beyond the spec's three: (azimuth, elevation) of P1, P2, P3 on the pivot sphere, deg
EXTRA_ARC_POINTS: tuple[tuple[tuple[float, float], ...], ...] = (
    ((-60.0, 45.0), (0.0, 45.0), (60.0, 45.0)),
    ((120.0, 30.0), (180.0, 30.0), (240.0, 30.0)),
    ((-150.0, 60.0), (-90.0, 60.0), (-30.0, 60.0)),
)
MAX_ARCS = 3 + len(EXTRA_ARC_POINTS)
# spec A.6 Table 5: dl1..dl6 (mm), dtheta1..dtheta6 (rad)
TABLE5_ERRORS = np.array(
    [0.4365, -0.4578, -0.0429, -0.0616, -0.4143, 0.0126, 0.0007, 0.0024, -0.0044, -0.0048, 0.0047, 0.0051]
)
SEED_DEG = np.array([0.0, 0.0, 0.0, 0.0, 90.0, 0.0])


def plan_arcs(
    k: int, pivot_mm: Sequence[float] = PAPER_PIVOT_MM, radius_mm: float = PAPER_RADIUS_MM
) -> tuple[Arc, ...]:
    """The first ``k`` arcs of a plan (module docstring), 1 ≤ k ≤ :data:`MAX_ARCS`."""
    if not 1 <= k <= MAX_ARCS:
        raise ValueError(f"arcs: 1..{MAX_ARCS}, got {k}")
    arcs = list(default_arcs(pivot_mm, radius_mm))
    for triple in EXTRA_ARC_POINTS:
        arcs.append(arc_through_points(*(sphere_point_mm(az, el, pivot_mm, radius_mm) for az, el in triple)))
    return tuple(arcs[:k])


def _rotation(
    params: KinematicParams, robot: RobotDescription, axes_deg: Sequence[float]
) -> NDArray[np.float64]:
    q = np.deg2rad(np.asarray([axes_deg], dtype=float)) * robot.sign
    return np.asarray(flange_pose(params, q)[0, :3, :3])


@dataclass(frozen=True, slots=True)
class BallbarPlan:
    """Axis values to command (n, 6), the arc of each point (1-based), the pivot and radius."""

    a_deg: NDArray[np.float64]
    arc: NDArray[np.intp]
    pivot_mm: NDArray[np.float64]
    radius_mm: float
    orientation: str
    step_deg: float


def ballbar_plan(
    robot: RobotDescription,
    k: int = 3,
    *,
    orientation: Orientation = "per-arc",
    pivot_mm: Sequence[float] = PAPER_PIVOT_MM,
    radius_mm: float = PAPER_RADIUS_MM,
    step_deg: float = 5.0,
) -> BallbarPlan:
    """The poses of a ``k``-arc ballbar campaign on ``robot`` (its TOML tool is the ball centre)."""
    if orientation not in ORIENTATIONS:
        raise ValueError(f"orientation: one of {', '.join(ORIENTATIONS)}, got {orientation!r}")
    if not 0.5 <= step_deg <= 45.0:
        raise ValueError(f"step: 0.5..45 deg, got {step_deg}")
    params = KinematicParams.from_robot(robot)
    arcs = plan_arcs(k, pivot_mm, radius_mm)
    choices = ORIENTATIONS[orientation]
    rotations = [_rotation(params, robot, choices[i % len(choices)]) for i in range(k)]
    a_deg, arc = plan_ballbar_axes(
        params, robot.sign, robot.axis_limits_deg, arcs, rotations, SEED_DEG, step_deg
    )
    return BallbarPlan(a_deg, arc, np.asarray(pivot_mm, dtype=float), radius_mm, orientation, step_deg)


@dataclass(frozen=True, slots=True)
class ArcCountRates:
    """Change rates of the mean and the variance of ‖ΔP‖ for each arc count, against the region."""

    arcs: tuple[int, ...]
    mean_rate: tuple[float, ...]
    variance_rate: tuple[float, ...]
    reference_mean_mm: float
    reference_variance_mm2: float

    @property
    def chosen(self) -> int:
        """The arc count with the smallest variance rate (spec A.6)."""
        return self.arcs[int(np.argmin(self.variance_rate))]


def _region_poses(
    robot: RobotDescription, n: int, rng: np.random.Generator, pivot_mm: Sequence[float], radius_mm: float
) -> NDArray[np.float64]:
    """Axis values of ``n`` random points of the measurement region (pivot sphere above ψ = 5°, the
    arcs' orientations), those the nominal inverse kinematics reaches."""
    params = KinematicParams.from_robot(robot)
    rots = np.array([_rotation(params, robot, r) for r in ORIENTATIONS["per-arc"]])
    az = rng.uniform(-180.0, 180.0, n)
    el = np.rad2deg(np.arcsin(rng.uniform(np.sin(np.deg2rad(5.0)), 1.0, n)))  # uniform on the cap
    pts = np.array([sphere_point_mm(a, e, pivot_mm, radius_mm) for a, e in zip(az, el, strict=True)])
    rot = rots[rng.integers(0, len(rots), n)]
    a_deg, res = solve_ik_axes(
        params, robot.sign, robot.axis_limits_deg, pts, rot, np.broadcast_to(SEED_DEG, (n, 6))
    )
    return np.asarray(a_deg[np.asarray(res.ok)])


def arc_count_rates(
    robot: RobotDescription,
    arcs: Sequence[int] = (2, 3, 4),
    *,
    errors: NDArray[np.float64] = TABLE5_ERRORS,
    orientation: Orientation = "per-arc",
    pivot_mm: Sequence[float] = PAPER_PIVOT_MM,
    radius_mm: float = PAPER_RADIUS_MM,
    n_region: int = 400,
    seed: int = 0,
) -> ArcCountRates:
    """Spec A.6's change rates of the plan's first k arcs (module docstring)."""
    model = PoeModel.from_robot(robot)
    region = _region_poses(robot, n_region, np.random.default_rng(seed), pivot_mm, radius_mm)
    ref = np.linalg.norm(_error_field(model, region, errors), axis=1)
    ref_mean, ref_var = float(ref.mean()), float(ref.var())
    mean_rate, var_rate = [], []
    for k in arcs:
        plan = ballbar_plan(robot, k, orientation=orientation, pivot_mm=pivot_mm, radius_mm=radius_mm)
        e = np.linalg.norm(_error_field(model, plan.a_deg, errors), axis=1)
        mean_rate.append(abs(float(e.mean()) - ref_mean) / ref_mean)
        var_rate.append(abs(float(e.var()) - ref_var) / ref_var)
    return ArcCountRates(tuple(arcs), tuple(mean_rate), tuple(var_rate), ref_mean, ref_var)


def variogram_table(
    robot: RobotDescription,
    lags_deg: Sequence[float] = (2.5, 5.0, 10.0, 20.0, 40.0, 60.0, 90.0, 120.0),
    *,
    errors: NDArray[np.float64] = TABLE5_ERRORS,
    n_poses: int = 1000,
    seed: int = 0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(lags deg, γ mm²) of the error field at exact joint-space lags from random poses in the limits."""
    rng = np.random.default_rng(seed)
    lim = robot.axis_limits_deg
    margin = 0.25 * (lim[:, 1] - lim[:, 0])  # room for the lag inside the limits
    base = rng.uniform(lim[:, 0] + margin, lim[:, 1] - margin, (n_poses, 6))
    gamma = error_variogram(PoeModel.from_robot(robot), errors, base, lags_deg, rng)
    return np.asarray(lags_deg, dtype=float), gamma
