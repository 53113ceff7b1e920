"""Synthetic measurement campaigns with chosen effects, for the blind tests of the diagnosis.

An independent generator: the "real" robot is the nominal description with random geometric errors
(``KinematicParams.apply``), a base frame error, optionally a tracker frame far from the base, and
the chosen non-geometric effects (``EffectParams`` of :mod:`comp_daemon.models.effects`). Poses are
drawn uniformly in a box of axis values, visited along a nearest-neighbour route that gives the
approach direction of every joint, some are measured several times (repeats); payload and
temperature vary over the campaign; the tracker adds Gaussian noise (σ per axis).

Effect sizes are set by what geometry cannot absorb: a unit effect's TCP signature is projected off
the 39 geometric columns of the campaign's poses and scaled so that the rest has the asked 3-D RMS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comp_daemon.data.dataset import Dataset
from comp_daemon.kinematics.forward import identification_jacobian
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects import EffectParams, effect_jacobian, effect_param_names, twin_tcp_mm
from comp_daemon.robot.description import RobotDescription, load_robot

NOISE_MM = 0.01
#: 3-D RMS of the tracker noise alone: the noise floor the sizes are measured against
NOISE_FLOOR_MM = NOISE_MM * np.sqrt(3.0)
TRUE_HARMONICS = 2

# box of axis values (deg) each robot is measured in
BOXES_DEG = {
    "KUKA KR 210 R2700 extra": [(-60, 60), (-115, -40), (40, 130), (-90, 90), (-100, 100), (-170, 170)],
    "ABB IRB 120": [(-90, 90), (-60, 60), (-80, 40), (-120, 120), (-100, 100), (-170, 170)],
    "Yaskawa MOTOMAN-MH6": [(-90, 90), (-40, 60), (-60, 60), (-120, 120), (-100, 100), (-170, 170)],
}
PAYLOADS_KG = {"KUKA KR 210 R2700 extra": (0.0, 60.0, 150.0), "ABB IRB 120": (0.0, 1.5, 3.0)}


@dataclass(frozen=True)
class Campaign:
    dataset: Dataset
    robot: RobotDescription
    effects: EffectParams  # the true non-geometric effects
    truth_dx: np.ndarray  # the true geometric errors (39)


def _route(a_deg: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Visiting order of a greedy nearest-neighbour route in axis space from ``start``."""
    n = len(a_deg)
    left = np.ones(n, dtype=bool)
    order = np.empty(n, dtype=np.int64)
    here = start
    for k in range(n):
        d = np.where(left, np.abs(a_deg - here).max(axis=1), np.inf)
        i = int(np.argmin(d))
        order[k] = i
        left[i] = False
        here = a_deg[i]
    return order


def sample_poses(robot: RobotDescription, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 6) axis values in the robot's box, in route order, and the (n, 6) approach directions."""
    box = np.array(BOXES_DEG[robot.name], dtype=float)
    lim = robot.axis_limits_deg
    lo, hi = np.maximum(box[:, 0], lim[:, 0]), np.minimum(box[:, 1], lim[:, 1])
    a = rng.uniform(lo, hi, size=(n, 6))
    home = 0.5 * (lo + hi)
    a = a[_route(a, home)]
    prev = np.vstack([home, a[:-1]])
    direction = np.where(a >= prev, 1.0, -1.0)
    return a, direction


def random_geometry(rng: np.random.Generator) -> np.ndarray:
    """A random 39-vector of geometric errors of industrial size."""
    dx = np.zeros(N_PARAMS)
    for j in range(6):
        dx[5 * j + 0] = np.deg2rad(rng.normal(0.0, 0.03))
        dx[5 * j + 1] = rng.normal(0.0, 0.3)
        dx[5 * j + 2] = rng.normal(0.0, 0.3)
        dx[5 * j + 3] = np.deg2rad(rng.normal(0.0, 0.03))
        dx[5 * j + 4] = np.deg2rad(rng.normal(0.0, 0.03))
    dx[30:33] = rng.normal(0.0, 1.0, 3)
    dx[33:36] = np.deg2rad(rng.normal(0.0, 0.05, 3))
    dx[36:39] = rng.normal(0.0, 0.3, 3)
    return dx


def tracker_transform(rng: np.random.Generator) -> np.ndarray:
    """A tracker frame metres away from the robot base and turned about every axis."""
    angles = rng.uniform(-np.pi, np.pi, 3) * np.array([0.1, 0.1, 1.0])
    cx, cy, cz = np.cos(angles)
    sx, sy, sz = np.sin(angles)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    out = np.eye(4)
    out[:3, :3] = rz @ ry @ rx
    out[:3, 3] = rng.uniform(-4000.0, 4000.0, 3)
    return out


def unit_effect(effect: str, joint: int | None, rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
    """Names and a unit direction of one effect on one joint (cyclic: random harmonic mix)."""
    names = effect_param_names(effect, () if joint is None else (joint,), TRUE_HARMONICS)
    if effect == "drift":
        names = names[:3]  # the rates: a linear drift in a random direction
    if effect in ("cyclic", "drift"):
        v = rng.normal(size=len(names))
    else:
        v = np.ones(len(names))
    return names, v / np.linalg.norm(v)


def sized_effects(
    robot: RobotDescription,
    a_deg: np.ndarray,
    direction: np.ndarray,
    payload: np.ndarray,
    temp: np.ndarray,
    withheld: list[tuple[str, int | None, float]],
    rng: np.random.Generator,
    *,
    clock: np.ndarray | None = None,
    step_at: float = float("inf"),
) -> EffectParams:
    """Effects whose TCP signature beyond geometry has the asked 3-D RMS (mm) each.

    ``clock`` (h) and ``step_at`` are the campaign clock and the step's moment of the time effects.
    """
    params = KinematicParams.from_robot(robot)
    zero = EffectParams.zeros(TRUE_HARMONICS, step_at=step_at)
    # a compliance of 1e-300 moves nothing but makes the effect model compute the gravity torques
    with_tau = zero.with_values(["C1"], [1e-300])
    geo = identification_jacobian(params, axes_deg_to_q_rad(a_deg, params.sign)).reshape(-1, N_PARAMS)
    norms = np.linalg.norm(geo, axis=0)
    geo = geo[:, norms > 1e-9 * norms.max()]
    u, sv, _ = np.linalg.svd(geo / np.linalg.norm(geo, axis=0), full_matrices=False)
    qmat = u[:, sv > 1e-9 * sv[0]]  # orthonormal basis of what geometry can absorb
    effects = zero
    for effect, joint, size_mm in withheld:
        names, v = unit_effect(effect, joint, rng)
        jac = effect_jacobian(robot, params, with_tau, names, a_deg, direction, payload, temp, clock=clock)
        sig = (jac @ v).reshape(-1)
        rest = sig - qmat @ (qmat.T @ sig)
        rms = np.sqrt(np.sum(rest**2) / len(a_deg))
        effects = effects.add(names, v * size_mm / rms * rng.choice([-1.0, 1.0]))
    return effects


def make_campaign(
    robot_name: str,
    seed: int,
    withheld: list[tuple[str, int | None, float]],
    *,
    n_poses: int = 240,
    repeat_fraction: float = 0.1,
    n_repeats: int = 3,
    check_fraction: float = 0.35,
    tracker: bool = False,
    noise_mm: float = NOISE_MM,
    joint_noise_deg: float = 0.0,
    with_dir: bool = True,
    with_temp: bool = True,
    payloads: tuple[float, ...] | None = None,
) -> Campaign:
    """A campaign of ``n_poses`` poses (plus repeats) with the ``withheld`` effects (effect, joint, mm).

    ``size`` in mm is the 3-D RMS of the effect's TCP signature that geometry cannot absorb; use
    multiples of :data:`NOISE_FLOOR_MM`.
    """
    rng = np.random.default_rng(seed)
    robot = load_robot(robot_name)
    a, direction = sample_poses(robot, n_poses, rng)
    loads = payloads if payloads is not None else PAYLOADS_KG.get(robot.name, (0.0,))
    payload = rng.choice(np.array(loads, dtype=float), size=n_poses)
    temp = 18.0 + 8.0 * np.linspace(0.0, 1.0, n_poses) + rng.normal(0.0, 0.2, n_poses)
    effects = sized_effects(robot, a, direction, payload, temp, withheld, rng)

    # repeats: some poses measured again right away (same approach, same load)
    reps = np.ones(n_poses, dtype=np.int64)
    reps[rng.random(n_poses) < repeat_fraction] = n_repeats
    rows = np.repeat(np.arange(n_poses), reps)
    repeat = np.concatenate([np.arange(r) for r in reps])
    a_r, dir_r, load_r, temp_r = a[rows], direction[rows], payload[rows], temp[rows]

    dx = random_geometry(rng)
    truth = KinematicParams.from_robot(robot).apply(dx)
    if tracker:
        truth = truth.with_base(tracker_transform(rng) @ truth.world_T_base)
    a_true = a_r + rng.normal(0.0, joint_noise_deg, a_r.shape) if joint_noise_deg > 0 else a_r
    xyz = twin_tcp_mm(robot, truth, effects, a_true, dir_r, load_r, temp_r)
    xyz = xyz + rng.normal(0.0, noise_mm, xyz.shape)

    is_check = rng.random(n_poses) < check_fraction
    split = np.where(is_check[rows], "check", "fit")
    dataset = Dataset(
        a_deg=a_r,
        xyz_mm=xyz,
        dir=dir_r.astype(np.int8) if with_dir else None,
        payload_kg=load_r,
        temp_c=temp_r if with_temp else None,
        split=split,
        repeat=repeat,
        pose_id=tuple(f"P{i:04d}" for i in rows),
        source=f"synthetic:{robot_name}:{seed}",
    )
    return Campaign(dataset=dataset, robot=robot, effects=effects, truth_dx=dx)


# ---- campaigns from the simulated plant ----------------------------------------------------------
#: 3-D noise floor of the kr210-geometric plant's campaigns (tracker σ 0.01 mm per axis and joint
#: repeatability), as measured from repeated poses
PLANT_NOISE_FLOOR_MM = 0.026
#: a calibration campaign wider than seed 000's drilling box, for effects that need joint travel
WIDE_BOX = {
    "box_min_mm": np.array([1100.0, -900.0, 300.0]),
    "box_max_mm": np.array([2300.0, 900.0, 1600.0]),
    "abc_min_deg": np.full(3, -30.0),
    "abc_max_deg": np.full(3, 30.0),
}


def plant_scenario(name: str, effects: EffectParams, *, wide: bool, temp_drift_k_per_h: float | None = None):
    """A plant scenario with ``effects`` in place of its own, optionally a wider box or a faster drift."""
    import dataclasses

    from comp_daemon.sim.scenario import load_scenario

    sc = load_scenario(name)
    sc = dataclasses.replace(sc, effects=effects)
    if wide:
        sc = dataclasses.replace(sc, campaign=dataclasses.replace(sc.campaign, **WIDE_BOX))
    if temp_drift_k_per_h is not None:
        sc = dataclasses.replace(sc, cell=dataclasses.replace(sc.cell, temp_drift_k_per_h=temp_drift_k_per_h))
    return sc


def plant_campaign(
    withheld: list[tuple[str, int | None, float]],
    seed: int,
    *,
    scenario: str = "kr210-geometric",
    n_poses: int = 160,
    repeats: int = 1,
    wide: bool = True,
    tracker: bool = False,
    temp_drift_k_per_h: float = 40.0,
    payloads: tuple[float, ...] | None = None,
    step_fraction: float = 0.5,
) -> Campaign:
    """A campaign of the simulated plant with the ``withheld`` effects, sized like :func:`make_campaign`.

    The plant runs twice with the same seed: without effects (poses, directions, loads, times and
    temperatures do not depend on them) to size the effects on those poses, then with them. A
    withheld ``step`` happens at ``step_fraction`` of the campaign's time; ``payloads`` replaces the
    scenario's.
    """
    from comp_daemon.sim.campaign import run_campaign

    sc = plant_scenario(
        scenario, EffectParams.zeros(TRUE_HARMONICS), wide=wide, temp_drift_k_per_h=temp_drift_k_per_h
    )
    if payloads is not None:
        import dataclasses

        sc = dataclasses.replace(sc, campaign=dataclasses.replace(sc.campaign, payload_kg=payloads))
    effects = EffectParams.zeros(TRUE_HARMONICS)
    if withheld:
        ds0 = run_campaign(sc, n_poses, seed=seed, repeats=repeats)
        assert ds0.dir is not None and ds0.temp_c is not None and ds0.t_s is not None
        clock = np.asarray(ds0.t_s) / 3600.0
        effects = sized_effects(
            sc.robot,
            np.asarray(ds0.a_deg),
            np.asarray(ds0.dir, dtype=float),
            np.asarray(ds0.payload_kg),
            np.asarray(ds0.temp_c),
            withheld,
            np.random.default_rng(seed + 99),
            clock=clock,
            step_at=float(clock.min() + step_fraction * np.ptp(clock)),
        )
    import dataclasses

    sc = dataclasses.replace(sc, effects=effects)
    ds = run_campaign(sc, n_poses, seed=seed, repeats=repeats, in_tracker_frame=tracker)
    return Campaign(dataset=ds, robot=sc.robot, effects=effects, truth_dx=sc.true_dx())


#: two further reflectors on the flange (mm, flange frame), off axis 6 as on a tracker nest
FURTHER_TARGETS_MM = np.array([[87.0, 0.0, 20.0], [-40.0, 75.0, 20.0]])


def wrist_campaign(seed: int, backlash6_deg: float, *, n_poses: int = 260) -> Campaign:
    """An IRB 120 campaign (TCP on axis 6) with three reflectors per pose: the TCP and
    :data:`FURTHER_TARGETS_MM`, small random geometry and a backlash of joint 6 (deg) that only the
    further reflectors can show; tracker noise :data:`NOISE_MM` per axis, 30 % check rows."""
    from comp_daemon.models.effects import MassModel, twin_state

    rng = np.random.default_rng(seed)
    robot = load_robot("irb120")
    a, direction = sample_poses(robot, n_poses, rng)
    dx = random_geometry(rng) * 0.3
    truth = KinematicParams.from_robot(robot).apply(dx)
    effects = EffectParams.zeros(TRUE_HARMONICS).with_values(["h6"], [backlash6_deg])
    payload = np.zeros(n_poses)
    st = twin_state(MassModel.from_robot(robot), truth, effects, a, direction, payload, None)
    flange = st.chain.world_T_frame[:, 6]
    rot, origin = flange[:, :3, :3], flange[:, :3, 3]
    tcp = st.tcp_mm + rng.normal(0.0, NOISE_MM, (n_poses, 3))
    more = origin[:, None] + np.einsum("nij,kj->nki", rot, FURTHER_TARGETS_MM)
    more = more + rng.normal(0.0, NOISE_MM, more.shape)
    dataset = Dataset(
        a_deg=a,
        xyz_mm=tcp,
        more_xyz_mm=more,
        dir=direction.astype(np.int8),
        payload_kg=payload,
        split=np.where(rng.random(n_poses) < 0.3, "check", "fit"),
        source=f"synthetic:irb120:wrist:{seed}",
    )
    return Campaign(dataset=dataset, robot=robot, effects=effects, truth_dx=dx)
