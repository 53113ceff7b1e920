"""Measurement campaigns on the simulated cell: sampling, ISO 9283 multi-direction test, raw error figures.

Sampling (seeds 000 and 001): a Latin hypercube over the six dimensions x, y, z (the scenario's box,
robot base frame, mm) and A, B, C (its ranges, deg; KUKA angles of the tool frame, whose x is the
flange's z, see :data:`FLANGE_R_KUKA_TOOL`). Inverse kinematics of the *nominal* robot (what the
controller computes) turns each target into commanded axis values; a target without a solution
inside the axis limits is redrawn uniformly. The poses are visited along a nearest-neighbour route
(in axis travel time) by the plant's PTP motion, one block per payload, so the ``dir`` columns
come from the motion. At each pose the plant settles, dwells, and the tracker measures the TCP.

ISO 9283 (7.2.4 multi-directional pose accuracy variation, 7.2.3 pose repeatability): poses on the
box diagonal, each approached ``n_cycles`` times from three mutually perpendicular directions
(start points ``approach_mm`` along +x, +y, +z of the base frame). ``vAP`` is the largest distance
between the barycentres of the three directions; ``RP = l̄ + 3·S_l`` the repeatability of one
direction (l: distances of the attained positions to their barycentre).

A re-stationed tracker (``restation``): the tracker is moved half-way through the campaign (by
measuring order, a second session): the rows from then on are station ``B``, measured in a frame
turned by :data:`RESTATION_ANGLE_DEG` about the vertical and moved :data:`RESTATION_SHIFT_MM` from
station ``A``'s (the scenario's tracker frame, or the robot base frame).

A 6-DOF probe (``probe_sigma_deg``): the probe's frame sits on the flange with its origin at the TCP
and a fixed hidden rotation (:data:`PROBE_MOUNT_ROTVEC`); each row gives its orientation
(``qw…qz``, in the tracker's frame, turned by a normal rotation vector of ``probe_sigma_deg`` per
axis) and ``sigma_mm``, the tracker's σ per axis.

Several targets (``targets`` > 1): reflectors fixed to the flange beside the TCP
(:func:`reflector_offsets_mm`), measured at every pose with independent tracker noise each and
written as the columns ``x2, y2, z2`` … of the data set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from comp_daemon.data.dataset import Dataset
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.inverse import solve_ik
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad, q_rad_to_axes_deg
from comp_daemon.kinematics.so3 import rotvec_to_matrix
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.scenario import Scenario
from comp_daemon.sim.tracker import LaserTracker

__all__ = [
    "GRATING_RESOLUTION_MM",
    "Iso9283Result",
    "RawErrorStats",
    "SampledPoses",
    "iso9283_multidirection",
    "measure_at",
    "nearest_neighbour_route",
    "raw_error_stats",
    "reflector_offsets_mm",
    "run_campaign",
    "sample_poses",
    "solve_axes",
    "visit_order",
]

GRATING_RESOLUTION_MM = 50e-6
DT_S = 0.012
REFLECTOR_RADIUS_MM = 150.0
MAX_TARGETS = 7
#: the second station's frame: turned this much about the vertical and moved this far from the first
RESTATION_ANGLE_DEG = 50.0
RESTATION_SHIFT_MM = (3000.0, 4000.0, 0.0)  # 5 m
#: the simulated 6-DOF probe's rotation on the flange (rotation vector, rad), unknown to the fits
PROBE_MOUNT_ROTVEC = (0.2, -0.1, 0.7)


def reflector_offsets_mm(tool_xyz_mm: NDArray[np.float64], targets: int) -> NDArray[np.float64]:
    """(targets, 3) positions of the reflectors in the flange frame (mm): the first at the TCP
    (``tool_xyz_mm``), the others :data:`REFLECTOR_RADIUS_MM` from it in the flange's x-y plane,
    60° apart (three targets: an equilateral triangle of 150 mm sides; up to seven: a hexagon)."""
    if not 1 <= targets <= MAX_TARGETS:
        raise ValueError(f"targets: between 1 and {MAX_TARGETS} reflectors, got {targets}")
    phi = np.deg2rad(60.0 * np.arange(targets - 1))
    ring = REFLECTOR_RADIUS_MM * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    tool = np.asarray(tool_xyz_mm, dtype=float)
    return np.concatenate([tool[None, :], tool + ring], axis=0)


@dataclass(frozen=True, slots=True)
class SampledPoses:
    target_xyz_mm: NDArray[np.float64]  # (n, 3) robot base frame
    target_abc_deg: NDArray[np.float64]  # (n, 3)
    a_deg: NDArray[np.float64]  # (n, 6) commanded axis values (nominal inverse kinematics)
    redrawn: int  # targets that had to be drawn again (unreachable)


def _limits_q_rad(params: KinematicParams, limits_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.sort(axes_deg_to_q_rad(limits_deg, params.sign[:, None]), axis=1)


def solve_axes(
    scenario: Scenario,
    xyz_mm: NDArray[np.float64],
    abc_deg: NDArray[np.float64],
    seed_axes_deg: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Nominal IK of TCP targets (xyz, KUKA A/B/C); returns axis values (n, 6) deg and ok (n,)."""
    params = KinematicParams.from_robot(scenario.robot)
    limits = _limits_q_rad(params, scenario.robot.axis_limits_deg)
    target_r = flange_rotation_of_tool_abc(abc_deg)
    seed = scenario.campaign.home_deg if seed_axes_deg is None else seed_axes_deg
    q_seed = np.broadcast_to(axes_deg_to_q_rad(np.asarray(seed, dtype=float), params.sign), (len(xyz_mm), 6))
    res = solve_ik(params, limits, xyz_mm, target_r, q_seed)
    return q_rad_to_axes_deg(res.q_rad, params.sign), res.ok


def sample_poses(scenario: Scenario, n: int, rng: np.random.Generator, max_rounds: int = 20) -> SampledPoses:
    """``n`` Latin-hypercube targets in the scenario's box and A/B/C ranges, with their axis values."""
    if n < 1:
        raise ValueError(f"n: need at least one pose, got {n}")
    cam = scenario.campaign
    lo = np.concatenate([cam.box_min_mm, cam.abc_min_deg])
    hi = np.concatenate([cam.box_max_mm, cam.abc_max_deg])
    unit = qmc.LatinHypercube(d=6, seed=rng).random(n)
    x = lo + unit * (hi - lo)
    a_deg, ok = solve_axes(scenario, x[:, :3], x[:, 3:])
    redrawn = 0
    for _ in range(max_rounds):
        bad = np.flatnonzero(~ok)
        if bad.size == 0:
            break
        redrawn += bad.size
        x[bad] = lo + rng.random((bad.size, 6)) * (hi - lo)
        a_deg[bad], ok[bad] = solve_axes(scenario, x[bad, :3], x[bad, 3:])
    if not ok.all():
        raise ValueError(
            f"scenario {scenario.name}: {int((~ok).sum())} targets stay unreachable after {max_rounds} "
            "redraws; the box or the A/B/C ranges lie outside the workspace"
        )
    return SampledPoses(x[:, :3].copy(), x[:, 3:].copy(), a_deg, redrawn)


def nearest_neighbour_route(
    a_deg: NDArray[np.float64], start_deg: NDArray[np.float64], v_max_deg_s: NDArray[np.float64]
) -> NDArray[np.intp]:
    """Visiting order: always the unvisited pose with the shortest synchronous PTP time (max |Δ|/v)."""
    n = len(a_deg)
    order = np.empty(n, dtype=np.intp)
    left = np.ones(n, dtype=bool)
    here = np.asarray(start_deg, dtype=float)
    for k in range(n):
        cost = np.abs(a_deg - here) / v_max_deg_s
        time = np.where(left, cost.max(axis=1), np.inf)
        nxt = int(np.argmin(time))
        order[k] = nxt
        left[nxt] = False
        here = a_deg[nxt]
    return order


@dataclass(frozen=True, slots=True)
class Measurement:
    xyz_mm: NDArray[np.float64]  # (3,) tracker reading
    tcp_true_mm: NDArray[np.float64]  # (3,) robot base frame, noise-free
    dir: NDArray[np.int8]  # (6,)
    g_deg: NDArray[np.float64]  # (6,) grating reading (quantised output angle)
    t_s: float
    temp_c: float
    more_xyz_mm: NDArray[np.float64] | None = None  # (K − 1, 3) tracker readings of further reflectors
    probe_r: NDArray[np.float64] | None = None  # (3, 3) a 6-DOF probe's orientation, tracker frame


def measure_at(
    plant: RobotPlant,
    tracker: LaserTracker,
    a_deg: NDArray[np.float64],
    dwell_s: float,
    radius_mm: float,
    more_flange_xyz_mm: NDArray[np.float64] | None = None,
    probe_sigma_deg: float | None = None,
) -> Measurement:
    """Move to ``a_deg``, settle, dwell, and measure (tracker, directions, gratings, time, temperature).

    ``more_flange_xyz_mm`` (K − 1, 3): further reflectors on the flange (flange frame), measured
    with the TCP, each with its own tracker noise. ``probe_sigma_deg``: a 6-DOF probe at the TCP
    reports its orientation too (flange · :data:`PROBE_MOUNT_ROTVEC`, with that noise per axis).
    """
    plant.move_to(a_deg)
    plant.run_until_settled(DT_S)
    if dwell_s > 0.0:
        plant.step(dwell_s)
    true = plant.tcp_true_mm()
    out = plant.output_angles_deg()
    counts = np.round(np.deg2rad(out) * radius_mm / GRATING_RESOLUTION_MM)
    more = None
    if more_flange_xyz_mm is not None and len(more_flange_xyz_mm):
        both = tracker.measure(np.concatenate([true[None, :], plant.points_true_mm(more_flange_xyz_mm)]))
        measured, more = both[0], both[1:]
    else:
        measured = tracker.measure(true)
    probe_r = None
    if probe_sigma_deg is not None:
        mount = rotvec_to_matrix(np.array(PROBE_MOUNT_ROTVEC))
        probe_r = tracker.measure_rotation(plant.flange_rotation_true() @ mount, probe_sigma_deg)
    return Measurement(
        xyz_mm=measured,
        tcp_true_mm=true,
        dir=plant.approach_dir(),
        g_deg=np.rad2deg(counts * GRATING_RESOLUTION_MM / radius_mm),
        t_s=plant.time_s,
        temp_c=plant.temperature_c(),
        more_xyz_mm=more,
        probe_r=probe_r,
    )


def _tracker(scenario: Scenario, seed: int, in_tracker_frame: bool, moved: bool = False) -> LaserTracker:
    frame = scenario.tracker_T_base() if in_tracker_frame else np.eye(4)
    if moved:  # the second station
        move = np.eye(4)
        move[:3, :3] = rotvec_to_matrix(np.array([0.0, 0.0, np.radians(RESTATION_ANGLE_DEG)]))
        move[:3, 3] = RESTATION_SHIFT_MM
        frame = move @ frame
    return LaserTracker(scenario.noise.tracker_sigma_mm, frame, seed=seed)


def visit_order(
    scenario: Scenario, a_deg: NDArray[np.float64], payload_of_pose: NDArray[np.float64]
) -> NDArray[np.intp]:
    """The order the poses ``a_deg`` (n, 6) are visited in: payload by payload (in the order of the
    scenario's ``payload_kg``: the load is changed once each), each group by the nearest-neighbour
    route in axis time from where the last one ended (the home pose first)."""
    parts = []
    here = scenario.campaign.home_deg
    for load in scenario.campaign.payload_kg:
        members = np.flatnonzero(payload_of_pose == load)
        if members.size == 0:
            continue
        sub = members[nearest_neighbour_route(a_deg[members], here, scenario.motion.v_max_deg_s)]
        parts.append(sub)
        here = a_deg[sub[-1]]
    return np.concatenate(parts)


def _grating_columns(meas: list[Measurement], joints: tuple[int, ...]) -> NDArray[np.float64] | None:
    """g1..g6 of the measurements: the grating joints' readings, NaN elsewhere (None without gratings)."""
    if not joints:
        return None
    g_deg = np.full((len(meas), 6), np.nan)
    cols = np.array(joints) - 1
    g_deg[:, cols] = np.array([m.g_deg for m in meas])[:, cols]
    return g_deg


def _measure_rounds(
    scenario: Scenario,
    plant: RobotPlant,
    trackers: tuple[LaserTracker, LaserTracker],
    a_deg: NDArray[np.float64],
    payload_kg: NDArray[np.float64],
    repeats: int,
    more_flange: NDArray[np.float64],
    probe_sigma_deg: float | None,
) -> list[Measurement]:
    """The poses ``a_deg`` in their order, ``repeats`` rounds, each with its payload (the plant's
    load changed only where it differs): the first tracker measures the first half of the rows, the
    second the rest (the same tracker unless the campaign moves it)."""
    meas: list[Measurement] = []
    total = repeats * len(a_deg)
    for _ in range(repeats):
        for a, load in zip(a_deg, payload_kg, strict=True):
            if plant.payload_kg != load:
                plant.set_payload(float(load))
            tracker = trackers[1] if 2 * len(meas) >= total else trackers[0]
            meas.append(
                measure_at(
                    plant,
                    tracker,
                    a,
                    scenario.motion.dwell_s,
                    scenario.cell.grating_radius_mm,
                    more_flange,
                    probe_sigma_deg,
                )
            )
    return meas


def run_campaign(
    scenario: Scenario,
    n: int,
    *,
    seed: int | None = None,
    repeats: int | None = None,
    in_tracker_frame: bool = False,
    gratings: bool = True,
    targets: int | None = None,
    restation: bool = False,
    probe_sigma_deg: float | None = None,
) -> Dataset:
    """A measurement campaign of ``n`` poses (× ``repeats``) on the scenario's hidden robot.

    ``seed`` (default: the scenario's campaign seed) drives the poses, the payload assignment, the
    split and all noise; the hidden robot is the scenario's own. ``in_tracker_frame`` reports
    x, y, z in the tracker frame of ``[cell]`` instead of the robot base frame. ``gratings`` adds
    g columns for the scenario's grating joints. ``targets`` (default: the scenario's) reflectors
    on the flange are measured at every pose (:func:`reflector_offsets_mm`; the hidden robot's tool
    is the first). ``restation``: the tracker moves to a second station half-way (module
    docstring); ``probe_sigma_deg``: a 6-DOF probe's orientation and ``sigma_mm`` on every row.
    """
    if probe_sigma_deg is not None and not (probe_sigma_deg >= 0 and np.isfinite(probe_sigma_deg)):
        raise ValueError(f"probe_sigma_deg: must be a finite number >= 0, got {probe_sigma_deg!r}")
    cam = scenario.campaign
    seed = cam.seed if seed is None else seed
    repeats = cam.repeats if repeats is None else repeats
    targets = cam.targets if targets is None else targets
    more_flange = reflector_offsets_mm(scenario.true_params().tool_xyz_mm, targets)[1:]
    if repeats < 1:
        raise ValueError(f"repeats: must be >= 1, got {repeats}")
    rng = np.random.default_rng(seed)
    poses = sample_poses(scenario, n, rng)
    payload_of_pose = rng.permutation(np.resize(np.asarray(cam.payload_kg), n))
    split_of_pose = np.full(n, "fit", dtype="<U5")
    n_check = round(cam.check_fraction * n)
    split_of_pose[rng.permutation(n)[:n_check]] = "check"

    plant = RobotPlant.from_scenario(scenario, seed=seed + 1)
    tracker = _tracker(scenario, seed + 2, in_tracker_frame)
    second = _tracker(scenario, seed + 3, in_tracker_frame, moved=True) if restation else tracker
    order = visit_order(scenario, poses.a_deg, payload_of_pose)

    trackers = (tracker, second)
    a_route, load_route = poses.a_deg[order], payload_of_pose[order]
    meas = _measure_rounds(
        scenario, plant, trackers, a_route, load_route, repeats, more_flange, probe_sigma_deg
    )
    total = len(meas)
    idx = np.tile(order, repeats)
    rows_rep = np.repeat(np.arange(repeats), len(order))
    g_deg = _grating_columns(meas, scenario.cell.grating_joints) if gratings else None
    return Dataset(
        a_deg=poses.a_deg[idx],
        xyz_mm=np.array([m.xyz_mm for m in meas]),
        dir=np.array([m.dir for m in meas]),
        g_deg=g_deg,
        payload_kg=payload_of_pose[idx],
        temp_c=np.array([m.temp_c for m in meas]),
        t_s=np.array([m.t_s for m in meas]),
        split=split_of_pose[idx],
        repeat=rows_rep,
        pose_id=tuple(f"p{p + 1:04d}" for p in idx),
        target_xyz_mm=poses.target_xyz_mm[idx],
        target_abc_deg=poses.target_abc_deg[idx],
        more_xyz_mm=np.array([m.more_xyz_mm for m in meas]) if targets > 1 else None,
        station=tuple("B" if 2 * k >= total else "A" for k in range(total)) if restation else None,
        probe_q_wxyz=None if probe_sigma_deg is None else _quaternions([m.probe_r for m in meas]),
        sigma_mm=None if probe_sigma_deg is None else np.full(total, scenario.noise.tracker_sigma_mm),
        source=f"sim:{scenario.name}:seed{seed}",
    )


def _quaternions(rotations: list[NDArray[np.float64] | None]) -> NDArray[np.float64]:
    """(n, 4) unit quaternions, w first (w ≥ 0), of the probe's measured rotations."""
    q = Rotation.from_matrix(np.array(rotations, dtype=float)).as_quat(scalar_first=True)
    return np.where(q[:, :1] < 0, -q, q)


@dataclass(frozen=True, slots=True)
class RawErrorStats:
    """Distances between the tracker and the nominal twin at the commanded axis values (mm)."""

    n: int
    max_mm: float
    mean_mm: float
    rms_mm: float
    axis_mean_mm: NDArray[np.float64]  # (3,) signed mean per x, y, z
    axis_max_abs_mm: NDArray[np.float64]  # (3,)


def raw_error_stats(scenario: Scenario, dataset: Dataset) -> RawErrorStats:
    """Raw error of a data set measured in the robot base frame: measured − nominal FK."""
    if dataset.a_deg is None or dataset.xyz_mm is None:
        raise ValueError("raw_error_stats: the data set needs a1..a6 and x, y, z")
    params = KinematicParams.from_robot(scenario.robot)
    nominal = tcp_position_mm(params, axes_deg_to_q_rad(dataset.a_deg, params.sign))
    err = dataset.xyz_mm - nominal
    dist = np.linalg.norm(err, axis=1)
    return RawErrorStats(
        n=len(dist),
        max_mm=float(dist.max()),
        mean_mm=float(dist.mean()),
        rms_mm=float(np.sqrt(np.mean(dist**2))),
        axis_mean_mm=err.mean(axis=0),
        axis_max_abs_mm=np.abs(err).max(axis=0),
    )


@dataclass(frozen=True, slots=True)
class Iso9283Result:
    points_mm: NDArray[np.float64]  # (p, 3) test poses
    vap_mm: NDArray[np.float64]  # (p,) multi-directional pose accuracy variation
    rp_mm: NDArray[np.float64]  # (p, 3) unidirectional pose repeatability per direction
    positions_mm: NDArray[np.float64]  # (p, 3, cycles, 3) attained positions (tracker)
    dirs: NDArray[np.int8]  # (p, 3, 6) approach directions of the axes (first cycle)

    @property
    def ratio(self) -> NDArray[np.float64]:
        """vAP / RP per pose (RP: the largest of the three directions)."""
        return self.vap_mm / self.rp_mm.max(axis=1)


def _rp(positions: NDArray[np.float64]) -> NDArray[np.float64]:
    """ISO 9283 pose repeatability of (..., cycles, 3) positions: l̄ + 3·S_l."""
    bary = positions.mean(axis=-2, keepdims=True)
    dist = np.linalg.norm(positions - bary, axis=-1)
    return dist.mean(axis=-1) + 3.0 * dist.std(axis=-1, ddof=1)


def iso9283_multidirection(
    scenario: Scenario,
    *,
    seed: int = 0,
    n_cycles: int = 30,
    approach_mm: float = 100.0,
    fractions: tuple[float, ...] = (0.2, 0.5, 0.8),
    payload_kg: float = 0.0,
) -> Iso9283Result:
    """ISO 9283 multi-directional pose accuracy variation on the scenario's hidden robot.

    Test poses at ``fractions`` of the box diagonal with the A/B/C ranges' centre orientation;
    each cycle approaches every pose from +x, +y and +z (``approach_mm`` away) in turn, after one
    unrecorded warm-up cycle (so that every recorded approach has the same motion history).
    """
    if n_cycles < 2:
        raise ValueError(f"n_cycles: at least 2 are needed for a repeatability, got {n_cycles}")
    cam = scenario.campaign
    points = np.array([cam.box_min_mm + f * (cam.box_max_mm - cam.box_min_mm) for f in fractions])
    abc = 0.5 * (cam.abc_min_deg + cam.abc_max_deg)
    offsets = np.eye(3) * approach_mm
    targets = np.concatenate([points[:, None, :], points[:, None, :] + offsets[None]], axis=1)  # (p, 4, 3)
    flat = targets.reshape(-1, 3)
    a_flat, ok = solve_axes(scenario, flat, np.broadcast_to(abc, flat.shape))
    if not ok.all():
        raise ValueError(f"scenario {scenario.name}: ISO 9283 test poses not reachable")
    a_deg = a_flat.reshape(len(points), 4, 6)
    plant = RobotPlant.from_scenario(scenario, seed=seed + 1, payload_kg=payload_kg)
    tracker = _tracker(scenario, seed + 2, False)
    positions = np.empty((len(points), 3, n_cycles, 3))
    dirs = np.zeros((len(points), 3, 6), dtype=np.int8)
    radius = scenario.cell.grating_radius_mm
    for p in range(len(points)):
        for cycle in range(-1, n_cycles):  # cycle −1 is an unrecorded warm-up of the same sequence
            for d in range(3):
                measure_at(plant, tracker, a_deg[p, 1 + d], 0.0, radius)
                m = measure_at(plant, tracker, a_deg[p, 0], scenario.motion.dwell_s, radius)
                if cycle >= 0:
                    positions[p, d, cycle] = m.xyz_mm
                if cycle == 0:
                    dirs[p, d] = m.dir
    bary = positions.mean(axis=2)  # (p, 3 directions, 3)
    gaps = np.linalg.norm(bary[:, :, None, :] - bary[:, None, :, :], axis=-1)
    return Iso9283Result(
        points_mm=points,
        vap_mm=gaps.max(axis=(1, 2)),
        rp_mm=_rp(positions),
        positions_mm=positions,
        dirs=dirs,
    )
