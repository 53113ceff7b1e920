"""Seed 000's rough + PD joint correction on a simulated joint with servo lag (pure, no I/O)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from comp_daemon.rt.controller import (
    JointLoopSettings,
    JointLoopState,
    LoopMode,
    hold_step,
    joint_step,
)

DEFAULT = JointLoopSettings()


def simulate(
    error0_deg: float,
    lag_cycles: int,
    *,
    settings: JointLoopSettings = DEFAULT,
    cycles: int = 400,
    noise_deg: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, list[LoopMode]]:
    """A joint that applies the step answered to telegram k at telegram k + 1 + lag_cycles.

    Returns the true error before each cycle, the steps sent and the loop mode of each cycle.
    """
    rng = np.random.default_rng(seed)
    target = 10.0 + error0_deg
    angle = 10.0
    sent: list[float] = []
    errors = np.empty(cycles)
    modes: list[LoopMode] = []
    state = JointLoopState()
    for k in range(cycles):
        if k - 1 - lag_cycles >= 0:
            angle += sent[k - 1 - lag_cycles]
        errors[k] = target - angle
        measured = angle + noise_deg * rng.standard_normal()
        res = joint_step(settings, state, target, measured, k * settings.cycle_s)
        state = res.state
        sent.append(res.step_deg)
        modes.append(state.mode)
    return errors, np.asarray(sent), modes


def settling_cycle(errors: np.ndarray, tol: float) -> int | None:
    inside = np.abs(errors) <= tol
    for k in range(errors.size):
        if inside[k:].all():
            return k
    return None


@pytest.mark.parametrize("lag", [1, 2])
@pytest.mark.parametrize("error0", [0.05, -0.03, 0.012, 0.005, -0.0025])
def test_step_response_settles_without_overshoot(lag: int, error0: float) -> None:
    errors, steps, _ = simulate(error0, lag)
    settle = settling_cycle(errors, 0.001)
    assert settle is not None and settle < 150, f"settling cycle {settle}"
    assert abs(errors[-1]) <= 0.001
    assert abs(errors[-1]) < 1e-5  # no integral term needed: the robot integrates the relative steps
    overshoot = max(0.0, float(-(errors * math.copysign(1.0, error0)).min()))
    assert overshoot <= 0.0005, f"overshoot {overshoot}"
    assert np.abs(steps).max() <= DEFAULT.max_step_deg + 1e-15


@pytest.mark.parametrize("lag", [1, 2])
def test_step_response_with_grating_noise_stays_within_a_thousandth(lag: int) -> None:
    # 50 nm on a 400 mm arc is 7e-6 deg; 2e-5 deg leaves room for vibration
    errors, _, _ = simulate(0.04, lag, noise_deg=2e-5, seed=lag)
    assert np.abs(errors[200:]).max() <= 0.001


def test_rough_mode_steps_exactly_until_the_threshold() -> None:
    errors, steps, modes = simulate(0.03, 1)
    rough = [k for k, m in enumerate(modes) if m is LoopMode.ROUGH]
    assert rough == list(range(len(rough)))  # rough first, then fine for good
    assert np.all(steps[rough] == DEFAULT.rough_step_deg)
    first_fine = len(rough)
    # the switch happens on the first cycle whose (measured) error is below 0.007 deg
    assert abs(errors[first_fine]) < DEFAULT.rough_threshold_deg
    assert abs(errors[first_fine - 1]) >= DEFAULT.rough_threshold_deg
    _, neg_steps, _ = simulate(-0.03, 1)
    assert neg_steps[0] == -DEFAULT.rough_step_deg


def test_fine_mode_is_the_pd_law_on_the_measurement() -> None:
    s = JointLoopSettings(kp=0.05, kd=0.65)
    state = JointLoopState(mode=LoopMode.FINE, total_deg=0.01, prev_measured_deg=1.000, prev_reading_t_s=0.0)
    res = joint_step(s, state, target_deg=1.004, measured_deg=1.001, reading_t_s=0.012)
    assert res.step_deg == pytest.approx(0.05 * 0.003 - 0.65 * 0.001, abs=1e-15)
    assert res.error_deg == pytest.approx(0.003)
    assert res.state.total_deg == pytest.approx(0.01 + res.step_deg)
    # a new target does not kick the D term: with the joint still, only the P part changes
    still = JointLoopState(mode=LoopMode.FINE, prev_measured_deg=1.001, prev_reading_t_s=0.0)
    a = joint_step(s, still, 1.004, 1.001, 0.012).step_deg
    b = joint_step(s, still, 1.005, 1.001, 0.012).step_deg
    assert b - a == pytest.approx(0.05 * 0.001, abs=1e-15)


def test_a_reading_already_used_gives_no_step() -> None:
    state = JointLoopState(mode=LoopMode.FINE, total_deg=0.01, prev_measured_deg=1.0, prev_reading_t_s=5.0)
    res = joint_step(DEFAULT, state, 1.004, 1.0, 5.0)
    assert res.step_deg == 0.0 and not res.fresh and res.state == state
    assert res.error_deg == pytest.approx(0.004)


def test_the_derivative_is_per_cycle_over_the_time_between_readings() -> None:
    s = JointLoopSettings(kp=0.0, kd=0.5, cycle_s=0.012)
    state = JointLoopState(mode=LoopMode.FINE, prev_measured_deg=1.0, prev_reading_t_s=0.0)
    # 0.003 deg in three cycles is 0.001 deg per cycle
    res = joint_step(s, state, 1.003, 1.003, 0.036)
    assert res.step_deg == pytest.approx(-0.5 * 0.001)
    # two readings 4 ms apart never count as less than a cycle (the D gain must not grow)
    res = joint_step(s, state, 1.001, 1.001, 0.004)
    assert res.step_deg == pytest.approx(-0.5 * 0.001)


@pytest.mark.parametrize("lag", [1, 2])
def test_readings_that_stall_in_bursts_do_not_make_the_loop_hunt(lag: int) -> None:
    """Grating polls delayed in bursts (a busy machine): no step without a new reading, and the
    derivative over the real time between readings — the loop still settles without overshoot."""
    rng = np.random.default_rng(lag)
    s = JointLoopSettings(max_step_deg=0.01)
    for error0 in (0.03, -0.012, 0.006):
        target, angle = 5.0 + error0, 5.0
        sent: list[float] = []
        state = JointLoopState()
        reading, reading_t, stall = angle, 0.0, 0
        errors = []
        for k in range(600):
            if k - 1 - lag >= 0:
                angle += sent[k - 1 - lag]
            if stall > 0:
                stall -= 1
            elif rng.random() < 0.15:
                stall = int(rng.integers(2, 8))
            else:
                reading, reading_t = angle, k * s.cycle_s
            errors.append(target - angle)
            res = joint_step(s, state, target, reading, reading_t)
            state = res.state
            sent.append(res.step_deg)
        e = np.asarray(errors)
        assert np.abs(e[300:]).max() <= 0.0005, (error0, np.abs(e[300:]).max())
        assert -(e * math.copysign(1.0, error0)).min() <= 0.001


def test_no_derivative_across_a_gap() -> None:
    state = JointLoopState(mode=LoopMode.FINE, prev_measured_deg=math.nan)
    res = joint_step(DEFAULT, state, 0.003, 0.0, 1.0)
    assert res.step_deg == pytest.approx(0.05 * 0.003)


def test_hysteresis_between_rough_and_fine() -> None:
    fine = JointLoopState(mode=LoopMode.FINE, prev_measured_deg=0.0, prev_reading_t_s=0.0)
    assert joint_step(DEFAULT, fine, 0.010, 0.0, 0.012).state.mode is LoopMode.FINE  # 0.007 <= 0.010 < 0.014
    assert joint_step(DEFAULT, fine, 0.020, 0.0, 0.012).state.mode is LoopMode.ROUGH
    rough = JointLoopState(mode=LoopMode.ROUGH)
    assert joint_step(DEFAULT, rough, 0.010, 0.0, 0.012).state.mode is LoopMode.ROUGH


def test_per_cycle_limit_clamps_and_reports() -> None:
    s = JointLoopSettings(kp=1.0, kd=0.0, max_step_deg=0.002)
    state = JointLoopState(mode=LoopMode.FINE, prev_measured_deg=0.0, prev_reading_t_s=0.0)
    res = joint_step(s, state, 0.005, 0.0, 0.012)
    assert res.step_deg == 0.002 and res.step_clamped and not res.total_limited
    res = joint_step(s, state, -0.005, 0.0, 0.012)
    assert res.step_deg == -0.002 and res.step_clamped


def test_total_limit_stops_the_total_exactly_at_the_limit() -> None:
    s = JointLoopSettings(max_total_deg=0.01)
    state = JointLoopState(total_deg=0.0095)
    res = joint_step(s, state, 1.0, 0.0, 0.0)  # rough step +0.002 would give 0.0115
    assert res.total_limited
    assert res.step_deg == pytest.approx(0.0005)
    assert res.state.total_deg == pytest.approx(0.01)
    res2 = joint_step(s, res.state, 1.0, 0.0, 0.012)
    assert res2.total_limited and res2.step_deg == 0.0 and res2.state.total_deg == pytest.approx(0.01)
    # moving back from the limit is allowed
    res3 = joint_step(s, res.state, -1.0, 0.0, 0.012)
    assert not res3.total_limited and res3.step_deg == -0.002


def test_runaway_with_an_inverted_sign_ends_at_the_total_limit() -> None:
    s = JointLoopSettings(max_total_deg=0.05)
    state = JointLoopState()
    angle, target, limited_at = 0.0, 0.02, None
    for k in range(200):
        res = joint_step(s, state, target, -angle, k * 0.012)  # grating mounted backwards, not calibrated
        state = res.state
        angle += res.step_deg
        if res.total_limited:
            limited_at = k
            break
    assert limited_at is not None
    assert abs(state.total_deg) <= 0.05 + 1e-12


def test_hold_keeps_the_total_and_sends_nothing() -> None:
    state = JointLoopState(mode=LoopMode.FINE, total_deg=0.02, prev_measured_deg=1.0, prev_reading_t_s=0.0)
    res = hold_step(state, 1.5, 0.012)
    assert res.step_deg == 0.0
    assert res.state.total_deg == 0.02
    assert (res.state.prev_measured_deg, res.state.prev_reading_t_s) == (1.5, 0.012)
    assert math.isnan(hold_step(state, None, None).state.prev_measured_deg)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"kp": -0.1}, "kp"),
        ({"kd": math.nan}, "kd"),
        ({"rough_step_deg": 0.0}, "rough_step_deg"),
        ({"rough_reenter_deg": 0.005}, "rough_reenter_deg"),
        ({"max_step_deg": 0.001}, "rough_step_deg"),
        ({"max_total_deg": 0.001, "max_step_deg": 0.002}, "max_step_deg"),
    ],
)
def test_bad_settings_are_refused_by_name(kwargs: dict[str, float], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        JointLoopSettings(**kwargs)


def _hunting_joint(settings: JointLoopSettings, lag: int, kick_deg: float) -> tuple[float, float]:
    """A joint whose output runs ahead of its motor over a band of ±h (gain 2 there; the simulated
    cell's play behaves so), a first-order servo (τ = 1.25 cycles) behind ``lag`` cycles of delay,
    and a three-cycle disturbance after it settled. Returns the last 200 cycles' max |error| and kd_scale.
    """
    h, tau = 0.006, 1.25
    motor = command = 0.0
    band = h
    target = 0.004 + h
    sent: list[float] = []
    state = JointLoopState()
    errors = []
    for k in range(900):
        if k - 1 - lag >= 0:
            command += sent[k - 1 - lag]
        new = command + (motor - command) * math.exp(-1.0 / tau)
        band = min(max(band + (new - motor), -h), h)
        motor = new
        out = motor + band
        res = joint_step(settings, state, target, out, k * settings.cycle_s)
        state = res.state
        sent.append(res.step_deg + (kick_deg if 200 <= k < 203 else 0.0))
        errors.append(target - out)
    return float(np.abs(np.asarray(errors[-200:])).max()), state.kd_scale


@pytest.mark.parametrize("kick", [0.004, -0.004, 0.008])
def test_the_hunting_guard_ends_a_limit_cycle(kick: float) -> None:
    unguarded = JointLoopSettings(max_step_deg=0.01, hunt_crossings=10**9)
    amplitude, scale = _hunting_joint(unguarded, 3, kick)
    assert amplitude > 0.01 and scale == 1.0  # kD = 0.65 hunts at about the band's width
    amplitude, scale = _hunting_joint(JointLoopSettings(max_step_deg=0.01), 3, kick)
    assert amplitude < 1e-4 and scale == 0.5


def test_the_guard_stays_out_of_a_normal_approach() -> None:
    for lag in (1, 2):
        for error0 in (0.05, -0.03, 0.005):
            state = JointLoopState()
            angle, target, sent = 0.0, error0, []
            for k in range(300):
                if k - 1 - lag >= 0:
                    angle += sent[k - 1 - lag]
                res = joint_step(DEFAULT, state, target, angle, k * DEFAULT.cycle_s)
                state = res.state
                assert not res.kd_reduced
                sent.append(res.step_deg)
            assert state.kd_scale == 1.0 and state.for_new_target().crossings == 0
