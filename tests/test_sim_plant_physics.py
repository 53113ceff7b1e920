"""The simulated plant: motion, approach directions, play, compliance, corrections, thermal state."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.robot.description import load_robot
from comp_daemon.sim.plant import RobotPlant, TrapezoidProfile
from comp_daemon.sim.rsi_controller import JointStateSource
from comp_daemon.sim.scenario import CellSettings, MotionSettings, load_scenario

ROBOT = load_robot("kr210")
NOMINAL = KinematicParams.from_robot(ROBOT)
MOTION = MotionSettings(
    v_max_deg_s=np.array([100.0, 90.0, 90.0, 150.0, 150.0, 200.0]),
    a_max_deg_s2=np.array([200.0, 180.0, 180.0, 300.0, 300.0, 400.0]),
    servo_time_constant_s=0.015,
    settle_tol_deg=1e-7,
)
HOME = np.array([0.0, -85.0, 125.0, 0.0, -40.0, 0.0])


def plant(effects: EffectParams | None = None, **kw) -> RobotPlant:
    return RobotPlant(ROBOT, NOMINAL, effects or EffectParams(), MOTION, start_axes_deg=HOME, **kw)


def fk(a_deg: np.ndarray) -> np.ndarray:
    return tcp_position_mm(NOMINAL, axes_deg_to_q_rad(np.atleast_2d(a_deg), NOMINAL.sign))


def go(p: RobotPlant, a_deg: np.ndarray) -> None:
    p.move_to(a_deg)
    p.run_until_settled(0.012)


def test_plant_without_errors_is_the_nominal_forward_kinematics() -> None:
    rng = np.random.default_rng(0)
    p = plant()
    for _ in range(5):
        target = HOME + rng.uniform(-20, 20, 6)
        go(p, target)
        np.testing.assert_allclose(p.axis_actual_deg(), target, atol=1e-7)
        np.testing.assert_allclose(p.tcp_true_mm(), fk(p.axis_actual_deg())[0], atol=1e-9)
        np.testing.assert_allclose(p.tcp_true_mm(), fk(target)[0], atol=1e-4)
        np.testing.assert_allclose(p.output_angles_deg(), p.axis_actual_deg(), atol=1e-12)


def test_trapezoid_is_synchronous_and_within_limits() -> None:
    start = np.zeros(6)
    target = np.array([60.0, -10.0, 5.0, 0.0, 90.0, -30.0])
    prof = TrapezoidProfile.plan(start, target, MOTION.v_max_deg_s, MOTION.a_max_deg_s2)
    t = np.linspace(0.0, prof.duration_s, 2001)
    pos = np.array([prof.position_deg(x) for x in t])
    vel = np.diff(pos, axis=0) / np.diff(t)[:, None]
    acc = np.diff(vel, axis=0) / np.diff(t)[1:, None]
    assert np.all(np.abs(vel) <= MOTION.v_max_deg_s * (1 + 1e-6))
    assert np.all(np.abs(acc) <= MOTION.a_max_deg_s2 * 1.01)
    # the limiting axis reaches its speed limit; all arrive together; each axis moves monotonically
    assert np.max(np.abs(vel) / MOTION.v_max_deg_s) > 0.99
    np.testing.assert_allclose(pos[-1], target, atol=1e-12)
    np.testing.assert_allclose(pos[0], start, atol=1e-12)
    assert np.all(np.diff(pos, axis=0) * np.sign(target - start) >= -1e-12)
    # a short move is triangular
    short = TrapezoidProfile.plan(start, np.full(6, 0.5), MOTION.v_max_deg_s, MOTION.a_max_deg_s2)
    assert short.duration_s == pytest.approx(2 * np.sqrt(0.5 / 180.0))


def test_setpoint_actual_and_settling() -> None:
    p = plant()
    target = HOME + np.array([30.0, 5.0, -5.0, 10.0, 10.0, 10.0])
    p.move_to(target)
    p.step(0.2)
    assert p.in_motion() and not p.settled
    lag = p.axis_setpoint_deg() - p.axis_actual_deg()
    assert lag[0] > 0  # servo lag behind a rising setpoint
    spent = p.run_until_settled(0.012)
    assert not p.in_motion() and p.settled
    assert spent > 0.0
    np.testing.assert_array_equal(p.axis_setpoint_deg(), target)


def test_approach_direction_comes_from_the_motion() -> None:
    p = plant()
    np.testing.assert_array_equal(p.approach_dir(), np.ones(6))
    go(p, HOME + np.array([5.0, -5.0, 0.0, 2.0, 0.0, -3.0]))
    np.testing.assert_array_equal(p.approach_dir(), [1, -1, 1, 1, 1, -1])  # unmoved axes keep +1
    go(p, HOME + np.array([-5.0, 0.0, -1.0, 4.0, 0.0, -3.0]))
    np.testing.assert_array_equal(p.approach_dir(), [-1, 1, -1, 1, 1, -1])


def test_backlash_gives_different_positions_from_opposite_directions() -> None:
    h = np.array([0.006, 0.005, 0.006, 0.004, 0.004, 0.004])
    eff = replace(EffectParams(), backlash_deg=h)
    p = plant(eff)
    target = HOME + np.array([10.0, 3.0, -4.0, 5.0, 5.0, 5.0])
    go(p, target - 2.0)
    go(p, target)
    from_below = p.tcp_true_mm()
    # a play lags: arriving from below, the output trails the motor by the play's half-width
    np.testing.assert_allclose(p.output_angles_deg() - p.axis_actual_deg(), -h, atol=1e-9)
    go(p, target + 2.0)
    go(p, target)
    from_above = p.tcp_true_mm()
    np.testing.assert_allclose(p.output_angles_deg() - p.axis_actual_deg(), h, atol=1e-9)
    gap = np.linalg.norm(from_below - from_above)
    assert gap > 0.2  # mm: the play of six joints at a 2 m reach
    ones = np.ones((1, 6))
    twin_eff = replace(eff, backlash_deg=-h)  # the twin's h of a play is negative (diagnose.md: A + h·dir)
    np.testing.assert_allclose(
        from_above, twin_tcp_mm(ROBOT, NOMINAL, twin_eff, target[None], -ones)[0], atol=1e-4
    )
    np.testing.assert_allclose(
        from_below, twin_tcp_mm(ROBOT, NOMINAL, twin_eff, target[None], ones)[0], atol=1e-4
    )


def test_short_reversal_leaves_the_output_inside_the_play() -> None:
    eff = replace(EffectParams(), backlash_deg=np.full(6, 0.01))
    p = plant(eff)
    go(p, HOME + 1.0)
    before = p.output_angles_deg()
    go(p, HOME + 1.0 - 0.004)  # reversal shorter than the play 2h = 0.02 deg
    offset = p.output_angles_deg() - p.axis_actual_deg()
    np.testing.assert_allclose(offset, -0.01 + 0.004, atol=1e-6)
    # inside the play the output stands still while the motor turns
    np.testing.assert_allclose(p.output_angles_deg(), before, atol=1e-6)
    np.testing.assert_array_equal(p.approach_dir(), -np.ones(6))


def test_compliance_deflection_grows_with_payload() -> None:
    eff = replace(EffectParams(), compliance_rad_per_nm=np.array([0.0, 2e-8, 3e-8, 1e-7, 1e-7, 1e-7]))
    p = plant(eff)
    target = HOME + np.array([0.0, 10.0, -10.0, 0.0, 0.0, 0.0])
    go(p, target)
    rigid = fk(p.axis_actual_deg())[0]
    sag = []
    for load in (0.0, 50.0, 150.0):
        p.set_payload(load)
        sag.append(np.linalg.norm(p.tcp_true_mm() - rigid))
        expect = twin_tcp_mm(ROBOT, NOMINAL, eff, p.axis_actual_deg()[None], None, load)[0]
        np.testing.assert_allclose(p.tcp_true_mm(), expect, atol=1e-9)
    assert 0.0 < sag[0] < sag[1] < sag[2]


def test_corrections_move_actual_but_not_setpoint() -> None:
    p = plant()
    go(p, HOME)
    p.apply_correction(np.array([0.01, 0, 0, 0, 0, 0]))
    p.step(0.5)
    np.testing.assert_allclose(p.axis_actual_deg()[0], HOME[0] + 0.01, atol=1e-9)
    np.testing.assert_array_equal(p.axis_setpoint_deg(), HOME)
    p.add_correction(np.array([0.0, -0.02, 0, 0, 0, 0]))
    p.step(0.5)
    np.testing.assert_allclose(p.correction_deg()[:2], [0.01, -0.02])
    np.testing.assert_allclose(p.axis_actual_deg()[1], HOME[1] - 0.02, atol=1e-9)
    assert p.approach_dir()[1] == -1  # a correction is a motion too


def test_halt_stops_the_interpolator_and_queue() -> None:
    p = plant()
    p.move_to(HOME + 30.0)
    p.move_to(HOME - 30.0)
    p.step(0.1)
    p.halt()
    assert not p.in_motion()
    where = p.axis_setpoint_deg()
    p.run_until_settled(0.012)
    np.testing.assert_array_equal(p.axis_setpoint_deg(), where)


def test_queued_moves_run_in_order() -> None:
    p = plant()
    p.move_to(HOME + 5.0)
    p.move_to(HOME - 5.0)
    p.run_until_settled(0.012)
    np.testing.assert_allclose(p.axis_actual_deg(), HOME - 5.0, atol=1e-6)
    np.testing.assert_array_equal(p.approach_dir(), -np.ones(6))


def test_repeatability_noise_is_fresh_per_motion_and_seeded() -> None:
    sigma = np.full(6, 0.001)
    a, b = plant(joint_repeatability_deg=sigma, seed=3), plant(joint_repeatability_deg=sigma, seed=3)
    positions = []
    for p in (a, b):
        go(p, HOME + 5.0)
        first = p.tcp_true_mm()
        go(p, HOME)
        go(p, HOME + 5.0)
        positions.append((first, p.tcp_true_mm()))
    np.testing.assert_array_equal(positions[0][0], positions[1][0])
    spread = np.linalg.norm(positions[0][0] - positions[0][1])
    assert 0.0 < spread < 1.0


def test_temperature_follows_the_cell_and_grows_the_arm() -> None:
    cell = CellSettings(temp_start_c=20.0, temp_drift_k_per_h=3.6)  # 1 K per 1000 s
    eff = replace(EffectParams(), thermal_per_k=1.2e-5)
    p = plant(eff, cell=cell)
    go(p, HOME)
    before = p.tcp_true_mm()
    t0 = p.time_s
    p.step(1000.0)
    assert p.temperature_c() == pytest.approx(20.0 + (t0 + 1000.0) / 1000.0)
    grown = np.linalg.norm(p.tcp_true_mm() - before)
    assert 0.01 < grown < 0.05  # about 1.2e-5/K of a 2.5 m arm for one kelvin


def test_bad_input_is_named() -> None:
    p = plant()
    with pytest.raises(ValueError, match=r"A2 = 10\.0000 deg is outside the limits"):
        p.move_to(np.array([0.0, 10.0, 90.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="apply_correction"):
        p.apply_correction(np.zeros(5))
    with pytest.raises(ValueError, match="joint 7"):
        p.output_angle_deg(7)
    with pytest.raises(ValueError, match="payload_kg"):
        p.set_payload(-1.0)


def test_scenario_plant_serves_the_controller_protocol() -> None:
    p: JointStateSource = RobotPlant.from_scenario(load_scenario("kr210-cell"))
    p.start_move(HOME + 1.0)
    while p.in_motion():
        p.advance(0.012)
    p.apply_correction(np.zeros(6))
    np.testing.assert_allclose(p.axis_setpoint_deg(), HOME + 1.0)
    assert isinstance(p, RobotPlant)
    assert abs(p.output_angle_deg(2) - p.axis_actual_deg()[1]) < 0.1
