"""Ballbar and cross-bar campaigns on a scenario's hidden robot (seeds 002 and 003).

Ballbar (:func:`run_ballbar_campaign`): the plan of :func:`comp_daemon.instruments.ballbar_plan.ballbar_plan`
(k arcs about the pivot, one flange orientation per arc, nominal inverse kinematics: what the
controller is told to do) is driven on the plant; at each point, settled, the reading is the
distance of the true TCP to the true pivot (the nominal pivot plus an offset drawn once per
campaign) plus the instrument's noise. A row per reading; ``repeats`` runs the plan that many times
(``pose_id`` names the point, for the uncertainty mode).

Cross-bar (:func:`run_crossbar_campaign`): placements of spec B.5
(:func:`comp_daemon.instruments.crossbar.plan_crossbar`, bar length L); the probe is seated in each
socket: the axis values that put the hidden robot's TCP on the socket centre plus the seating error
(σ per axis), found on its geometry and then corrected once for what the plant adds (backlash,
joint repeatability), read back as the controller shows them.

Both write their form (``docs/data-format.md``, "Ballbar and cross-bar campaigns"), with a ``split`` of whole
arcs or placements when ``check`` asks for some.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.ballbar import ballbar_dataset
from comp_daemon.data.crossbar import crossbar_dataset
from comp_daemon.data.table import Dataset
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, PAPER_RADIUS_MM
from comp_daemon.instruments.ballbar_plan import Orientation, ballbar_plan
from comp_daemon.instruments.crossbar import CrossbarPlan, plan_crossbar, seat_probe
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import axes_deg_to_q_rad
from comp_daemon.sim.campaign import measure_at
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.scenario import Scenario
from comp_daemon.sim.tracker import LaserTracker

__all__ = [
    "BALLBAR_NOISE_MM",
    "CAMPAIGN_SCENARIOS",
    "PIVOT_OFFSET_SIGMA_MM",
    "SEATING_SIGMA_MM",
    "run_ballbar_campaign",
    "run_crossbar_campaign",
]

#: the scenario whose hidden robot a campaign form measures by default
CAMPAIGN_SCENARIOS: dict[str, str] = {"ballbar": "irb120-geometric", "crossbar": "mh6-cell"}
BALLBAR_NOISE_MM = 0.0005  # σ of a ballbar reading (spec A.9: 0.5 µm)
PIVOT_OFFSET_SIGMA_MM = 0.5  # σ per axis of the true pivot from its nominal position
SEATING_SIGMA_MM = 0.1  # σ per axis of a seated probe from the socket centre (spec B.5)


def _split(n_groups: int, check: int, rng: np.random.Generator) -> NDArray[np.str_] | None:
    if check <= 0:
        return None
    if check >= n_groups:
        raise ValueError(f"check: {check} of {n_groups} groups leaves none to fit")
    labels = np.full(n_groups, "fit", dtype="<U5")
    labels[rng.permutation(n_groups)[:check]] = "check"
    return labels


def run_ballbar_campaign(
    scenario: Scenario,
    *,
    arcs: int = 3,
    orientation: Orientation = "per-arc",
    pivot_mm: tuple[float, float, float] = PAPER_PIVOT_MM,
    radius_mm: float = PAPER_RADIUS_MM,
    seed: int = 0,
    repeats: int = 1,
    check_arcs: int = 0,
    noise_mm: float = BALLBAR_NOISE_MM,
) -> Dataset:
    """A ballbar campaign of ``arcs`` arcs on the scenario's hidden robot (module docstring)."""
    if repeats < 1:
        raise ValueError(f"repeats: must be >= 1, got {repeats}")
    rng = np.random.default_rng(seed)
    plan = ballbar_plan(scenario.robot, arcs, orientation=orientation, pivot_mm=pivot_mm, radius_mm=radius_mm)
    true_pivot = np.asarray(pivot_mm, dtype=float) + rng.normal(0.0, PIVOT_OFFSET_SIGMA_MM, 3)
    split_of_arc = _split(arcs, check_arcs, rng)
    plant = RobotPlant.from_scenario(scenario, seed=seed + 1)
    still = LaserTracker(0.0, np.eye(4), seed=seed + 2)
    n = len(plan.a_deg)
    bar, rows = [], []
    for _ in range(repeats):
        for i in range(n):
            m = measure_at(
                plant, still, plan.a_deg[i], scenario.motion.dwell_s, scenario.cell.grating_radius_mm
            )
            bar.append(float(np.linalg.norm(m.tcp_true_mm - true_pivot)) + rng.normal(0.0, noise_mm))
            rows.append(i)
    idx = np.array(rows)
    return ballbar_dataset(
        plan.a_deg[idx],
        plan.arc[idx],
        plan.pivot_mm,
        bar_mm=np.array(bar),
        split=None if split_of_arc is None else split_of_arc[plan.arc[idx] - 1],
        pose_id=tuple(f"b{i + 1:04d}" for i in idx),
        repeat=np.repeat(np.arange(repeats), n),
        source=f"sim:{scenario.name}:ballbar:seed{seed}",
    )


def run_crossbar_campaign(
    scenario: Scenario,
    *,
    placements: int = 18,
    bar_l_mm: float = 400.0,
    seed: int = 0,
    check_placements: int = 0,
    seating_sigma_mm: float = SEATING_SIGMA_MM,
    max_draws: int = 20,
) -> Dataset:
    """A cross-bar campaign of ``placements`` crosses on the scenario's hidden robot (module docstring)."""
    rng = np.random.default_rng(seed)
    robot = scenario.robot
    truth = scenario.true_params()
    total = placements + check_placements
    chosen_a: list[NDArray[np.float64]] = []
    chosen_l: list[float] = []
    for _ in range(max_draws):
        plan = plan_crossbar(total - len(chosen_a), rng, bar_l_mm=bar_l_mm)
        sockets = plan.sockets_mm.reshape(-1, 3) + rng.normal(
            0.0, seating_sigma_mm, (plan.sockets_mm.size // 3, 3)
        )
        seated = CrossbarPlan(sockets.reshape(plan.sockets_mm.shape), plan.flange_R, plan.bar_l_mm)
        a_deg, ok = seat_probe(truth, robot.sign, robot.axis_limits_deg, seated)
        for k in np.flatnonzero(ok):
            chosen_a.append(a_deg[k])
            chosen_l.append(float(plan.bar_l_mm[k]))
        if len(chosen_a) >= total:
            break
    if len(chosen_a) < total:
        raise ValueError(
            f"scenario {scenario.name}: only {len(chosen_a)} of {total} cross placements reachable"
        )
    a = np.array(chosen_a[:total])
    lengths = np.array(chosen_l[:total])
    a = _seat_on_plant(scenario, a, seed)
    return crossbar_dataset(
        a,
        lengths,
        split=_split(total, check_placements, rng),
        source=f"sim:{scenario.name}:crossbar:seed{seed}",
    )


def _seat_on_plant(scenario: Scenario, a_deg: NDArray[np.float64], seed: int) -> NDArray[np.float64]:
    """The readings once the plant's own effects are corrected for: at each seating the TCP the
    plant reaches is compared with the geometric one, and the axes moved by the nominal
    Jacobian's least-squares step that removes the difference."""
    robot = scenario.robot
    truth = scenario.true_params()
    plant = RobotPlant.from_scenario(scenario, seed=seed + 1)
    still = LaserTracker(0.0, np.eye(4), seed=seed + 2)
    flat = a_deg.reshape(-1, 6).copy()
    wanted = tcp_position_mm(truth, axes_deg_to_q_rad(flat, robot.sign))
    for i in range(len(flat)):
        m = measure_at(plant, still, flat[i], scenario.motion.dwell_s, scenario.cell.grating_radius_mm)
        miss = wanted[i] - m.tcp_true_mm
        jac = np.empty((3, 6))
        h = 1e-4
        for j in range(6):
            step = np.zeros(6)
            step[j] = h
            plus = tcp_position_mm(truth, axes_deg_to_q_rad((flat[i] + step)[None], robot.sign))[0]
            minus = tcp_position_mm(truth, axes_deg_to_q_rad((flat[i] - step)[None], robot.sign))[0]
            jac[:, j] = (plus - minus) / (2 * h)
        flat[i] = flat[i] + np.linalg.lstsq(jac, miss, rcond=None)[0]
    return flat.reshape(a_deg.shape)
