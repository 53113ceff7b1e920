"""The plant's time effects (a drift of the TCP, a step of a joint's zero) and the real-like scenario."""

from __future__ import annotations

import dataclasses
from importlib import resources

import numpy as np
import pytest

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects import EffectParams
from comp_daemon.robot.description import load_robot
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.scenario import PRESET_SCENARIOS, ScenarioError, load_scenario, parse_scenario_toml

ROBOT = load_robot("kr210")
NOMINAL = KinematicParams.from_robot(ROBOT)
HOME = np.array([0.0, -85.0, 125.0, 0.0, -40.0, 0.0])


def _plant(effects: EffectParams) -> RobotPlant:
    sc = load_scenario("kr210-geometric")
    return RobotPlant(ROBOT, NOMINAL, effects, sc.motion, start_axes_deg=HOME)


def test_drift_moves_the_tcp_with_plant_time_only() -> None:
    v = np.array([0.3, -0.1, 0.2])  # mm/h
    w = np.array([0.0, 0.0, -0.05])  # mm/h²
    eff = EffectParams.zeros(2).with_values(["vx", "vy", "vz", "wx", "wy", "wz"], [*v, *w])
    p = _plant(eff)
    start = p.tcp_true_mm()
    np.testing.assert_allclose(
        start, tcp_position_mm(NOMINAL, axes_deg_to_q_rad(HOME[None], NOMINAL.sign))[0]
    )
    p.step(7200.0)  # two hours standing still
    np.testing.assert_allclose(p.tcp_true_mm() - start, v * 2.0 + w * 4.0, atol=1e-9)
    assert np.allclose(p.output_angles_deg(), HOME)  # a drift moves no joint


def test_step_changes_one_joints_zero_from_its_moment_on() -> None:
    eff = dataclasses.replace(EffectParams.zeros(2), step_at=1.0).with_values(["sz3"], [0.01])
    p = _plant(eff)
    before = p.output_angles_deg()
    p.step(3599.0)
    np.testing.assert_allclose(p.output_angles_deg(), before)
    p.step(2.0)
    after = p.output_angles_deg()
    np.testing.assert_allclose(after - before, [0.0, 0.0, 0.01, 0.0, 0.0, 0.0], atol=1e-12)
    expect = tcp_position_mm(NOMINAL, axes_deg_to_q_rad(after[None], NOMINAL.sign))[0]
    np.testing.assert_allclose(p.tcp_true_mm(), expect, atol=1e-9)


def test_scenario_fields_of_the_time_effects() -> None:
    text = resources.files("comp_daemon.sim").joinpath("scenarios/kr210-backlash.toml").read_text("utf-8")
    extra = (
        "drift_mm_per_h = [0.1, 0.0, 0.2]\nstep_deg = [0.0, 0.005, 0.0, 0.0, 0.0, 0.0]\nstep_at_s = 1800.0\n"
    )
    head = "[effects]                        # backlash only\n"
    assert head in text
    sc = parse_scenario_toml(text.replace(head, head + extra), "t.toml")
    assert sc.effects.get(["vx", "vy", "vz", "sz2"]).tolist() == [0.1, 0.0, 0.2, 0.005]
    assert sc.effects.step_at == pytest.approx(0.5)
    with pytest.raises(ScenarioError, match="step_at_s"):
        parse_scenario_toml(text.replace(head, head + "step_deg = [0.0, 0.005, 0, 0, 0, 0]\n"), "t.toml")


def test_real_like_scenario_withholds_a_drift_no_column_names() -> None:
    assert "real-like" in PRESET_SCENARIOS
    sc = load_scenario("real-like")
    assert sc.noise.tracker_sigma_mm == pytest.approx(0.005)
    assert not sc.effects.is_zero(next(e for e in _catalogue() if e.name == "drift"))
    assert sc.cell.temp_drift_k_per_h == 0.0 and sc.effects.thermal_per_k == 0.0
    ds = run_campaign(sc, 40, seed=1, gratings=False)
    assert ds.temp_c is not None and np.ptp(ds.temp_c) == 0.0
    # nothing in the data names the drift: the true TCP moves with time at a fixed pose
    p = RobotPlant.from_scenario(sc)
    first = p.tcp_true_mm()
    p.step(3600.0)
    assert np.linalg.norm(p.tcp_true_mm() - first) > 0.1


def _catalogue():
    from comp_daemon.models.effects import EFFECT_CATALOGUE

    return EFFECT_CATALOGUE
