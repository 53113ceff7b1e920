"""The trial's poses: seed 000's ISO 9283 test points, sampling points and target points.

Everything is planned before the robot moves, from the scenario's box (robot base frame, mm) and
A/B/C ranges (KUKA angles of the tool frame, deg), with the *nominal* inverse kinematics a robot
program would use (:func:`comp_daemon.sim.campaign.solve_axes`):

- ISO 9283 multi-directional pose accuracy (seed 000 §3.1, Fig. 5): test points at ``iso_fractions``
  of the box diagonal, orientation the centre of the A/B/C ranges; each approached from a start
  point ``approach_mm`` along +x, +y and +z of the base frame (three mutually perpendicular
  directions of motion).
- Sampling and target points (seed 000 §3.2): ``n_sampling`` and ``n_targets`` poses drawn
  independently by Latin hypercube in the box and the A/B/C ranges, each visited along a
  nearest-neighbour route from the scenario's home, so the approach directions ``dir`` of every
  run over the same points are the same.

Units: mm, deg; axis values in the controller's convention (A1..A6).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.models.compensation import nominal_targets
from comp_daemon.models.nominal import NominalModel
from comp_daemon.sim.campaign import nearest_neighbour_route, sample_poses, solve_axes
from comp_daemon.sim.scenario import Scenario

__all__ = ["FULL", "QUICK", "PlannedPoints", "TrialPlan", "TrialSizes", "plan_trial", "visit_dirs"]


@dataclass(frozen=True, slots=True)
class TrialSizes:
    """How much the trial measures; :data:`FULL` is seed 000's experiment."""

    iso_fractions: tuple[float, ...] = (0.2, 0.5, 0.8)
    iso_cycles: int = 30
    iso_warmup_cycles: int = 1
    approach_mm: float = 100.0
    n_sampling: int = 100
    n_targets: int = 104
    chebyshev_order: int = 3
    dwell_s: float = 0.5  # open-loop standstill before the tracker reads (the campaigns' dwell)
    loop_sampling: bool = True  # sample (and fit the Chebyshev model) with the joint loop closed
    kinematic_with_loop: bool = True  # also run the targets with the kinematic model + the loop
    seed000_mapping: bool = True  # also run the Chebyshev targets with seed 000's joint mapping
    calibration_poses: int = 6  # grating calibration poses (each approached from both sides)

    def __post_init__(self) -> None:
        if not self.iso_fractions or not all(0.0 <= f <= 1.0 for f in self.iso_fractions):
            raise ValueError(f"iso_fractions: need values in [0, 1], got {self.iso_fractions}")
        if self.iso_cycles < 2:
            raise ValueError(f"iso_cycles: a repeatability needs at least 2 cycles, got {self.iso_cycles}")
        if self.iso_warmup_cycles < 0:
            raise ValueError(f"iso_warmup_cycles: must be >= 0, got {self.iso_warmup_cycles}")
        if self.n_sampling < 3 or self.n_targets < 2:
            raise ValueError(
                f"need at least 3 sampling and 2 target points, got {self.n_sampling} and {self.n_targets}"
            )
        if not 0 <= self.chebyshev_order <= 8:
            raise ValueError(f"chebyshev_order: 0..8, got {self.chebyshev_order}")
        if self.calibration_poses < 3:
            raise ValueError(f"calibration_poses: at least 3, got {self.calibration_poses}")
        if not (self.approach_mm > 0.0 and self.dwell_s >= 0.0):
            raise ValueError("approach_mm must be > 0 and dwell_s >= 0")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


FULL = TrialSizes()
#: The reduced trial of the test suite, through the running daemon: one ISO point, two cycles;
#: 32 sampling + 14 target points (46 rows: four more than the least a kinematic fit (27 identifiable
#: parameters on the fit rows) and an order-0 Chebyshev model (42 coefficients) accept, so a point
#: without a grating reading does not stop the trial); the Chebyshev model
#: fitted on the open-loop sampling (no second, closed-loop pass); three grating calibration poses.
QUICK = TrialSizes(
    iso_fractions=(0.5,),
    iso_cycles=2,
    iso_warmup_cycles=0,
    n_sampling=32,
    n_targets=14,
    chebyshev_order=0,
    dwell_s=0.1,
    loop_sampling=False,
    kinematic_with_loop=False,
    calibration_poses=3,
)


@dataclass(frozen=True, slots=True)
class TrialPlan:
    scenario: str = "kr210-cell"
    seed: int = 0  # poses, the simulated robot's noise and the tracker's noise
    payload_kg: float = 0.0
    sizes: TrialSizes = field(default_factory=TrialSizes)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "seed": self.seed,
            "payload_kg": self.payload_kg,
            "sizes": self.sizes.to_dict(),
        }


@dataclass(frozen=True, slots=True)
class PlannedPoints:
    """One set of points in visiting order: wanted TCP (base frame) and nominal commands."""

    name: str
    wanted_mm: NDArray[np.float64]  # (n, 3) robot base frame
    wanted_R: NDArray[np.float64]  # (n, 3, 3) flange orientation of the nominal commands
    abc_deg: NDArray[np.float64]  # (n, 3) KUKA A, B, C of the tool frame
    a_nominal_deg: NDArray[np.float64]  # (n, 6) nominal inverse kinematics
    dir: NDArray[np.float64]  # (n, 6) approach direction of each axis along the route (±1)

    @property
    def n(self) -> int:
        return int(self.a_nominal_deg.shape[0])


@dataclass(frozen=True, slots=True)
class IsoPoints:
    """ISO 9283 test points (p,) with their three start points; axis values of both."""

    points_mm: NDArray[np.float64]  # (p, 3)
    starts_mm: NDArray[np.float64]  # (p, 3 directions, 3)
    a_point_deg: NDArray[np.float64]  # (p, 6)
    a_start_deg: NDArray[np.float64]  # (p, 3, 6)
    abc_deg: NDArray[np.float64]  # (3,)


@dataclass(frozen=True, slots=True)
class TrialPoints:
    home_deg: NDArray[np.float64]
    iso: IsoPoints
    sampling: PlannedPoints
    targets: PlannedPoints


def visit_dirs(a_deg: NDArray[np.float64], start_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """Approach direction (±1) of every axis when the poses are visited in order from ``start_deg``:
    the sign of the axis' last motion (an axis that did not move keeps its previous sign; +1 before
    any motion)."""
    a = np.asarray(a_deg, dtype=float)
    prev = np.vstack([np.asarray(start_deg, dtype=float)[None, :], a[:-1]])
    step = np.sign(a - prev)
    rows = np.arange(a.shape[0])[:, None]
    last = np.maximum.accumulate(np.where(step != 0.0, rows, -1), axis=0)  # row of the last motion
    moved = np.take_along_axis(step, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, moved, 1.0)


def _points(name: str, scenario: Scenario, n: int, rng: np.random.Generator) -> PlannedPoints:
    poses = sample_poses(scenario, n, rng)
    home = np.asarray(scenario.campaign.home_deg, dtype=float)
    order = nearest_neighbour_route(poses.a_deg, home, scenario.motion.v_max_deg_s)
    a = poses.a_deg[order]
    wanted, rot = nominal_targets(NominalModel(scenario.robot), a)
    return PlannedPoints(
        name=name,
        wanted_mm=wanted,
        wanted_R=rot,
        abc_deg=poses.target_abc_deg[order],
        a_nominal_deg=a,
        dir=visit_dirs(a, home),
    )


def plan_trial(scenario: Scenario, plan: TrialPlan) -> TrialPoints:
    """All poses of the trial (module docstring); the same plan always gives the same poses."""
    sizes = plan.sizes
    cam = scenario.campaign
    rng = np.random.default_rng(plan.seed)
    sampling = _points("sampling", scenario, sizes.n_sampling, rng)
    targets = _points("targets", scenario, sizes.n_targets, rng)
    fr = np.asarray(sizes.iso_fractions, dtype=float)
    points = cam.box_min_mm + fr[:, None] * (cam.box_max_mm - cam.box_min_mm)
    starts = points[:, None, :] + sizes.approach_mm * np.eye(3)[None, :, :]
    abc = 0.5 * (cam.abc_min_deg + cam.abc_max_deg)
    flat = np.concatenate([points, starts.reshape(-1, 3)])
    a_flat, ok = solve_axes(scenario, flat, np.broadcast_to(abc, flat.shape))
    if not ok.all():
        raise ValueError(f"scenario {scenario.name}: an ISO 9283 test or start point is not reachable")
    p = len(points)
    iso = IsoPoints(
        points_mm=points,
        starts_mm=starts,
        a_point_deg=a_flat[:p],
        a_start_deg=a_flat[p:].reshape(p, 3, 6),
        abc_deg=abc,
    )
    return TrialPoints(np.asarray(cam.home_deg, dtype=float), iso, sampling, targets)
