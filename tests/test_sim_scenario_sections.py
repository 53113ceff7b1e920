"""The scenario file's tables, each read by its own parser: the rule of each table, and its refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from comp_daemon.robot.description import load_robot
from comp_daemon.sim.scenario import (
    ScenarioError,
    _count,
    _parse_campaign,
    _parse_cell,
    _parse_effects,
    _parse_geometric,
    _parse_header,
    _parse_motion,
    _parse_noise,
)

KR210 = load_robot("kr210")
BOX = {
    "box_min_mm": [0.0, 0.0, 0.0],
    "box_max_mm": [1.0, 1.0, 1.0],
    "home_deg": [0.0, -85.0, 125.0, 0.0, -40.0, 0.0],
}


@pytest.mark.parametrize(
    ("value", "least", "ok"),
    [
        (0, 0, True),
        (3, 1, True),
        (0, 1, False),
        (-1, 0, False),
        (True, 0, False),
        (1.0, 0, False),
        ("2", 0, False),
    ],
)
def test_count_takes_only_integers_of_at_least_its_floor(value: object, least: int, ok: bool) -> None:
    if ok:
        assert _count({"n": value}, "n", "w", 7, least=least) == value
    else:
        with pytest.raises(ScenarioError, match=rf"w\.n: expected an integer >= {least}"):
            _count({"n": value}, "n", "w", 7, least=least)
    assert _count({}, "n", "w", 7, least=least) == 7


def test_header_needs_a_name_and_a_robot_and_reads_the_seed() -> None:
    name, description, robot, seed = _parse_header(
        {"scenario": {"name": "s", "robot": "kr210", "seed": 4}}, "f"
    )
    assert (name, description, robot.name, seed) == ("s", "", KR210.name, 4)
    with pytest.raises(ScenarioError, match=r"f \[scenario\]: missing field 'name'"):
        _parse_header({"scenario": {"name": "", "robot": "kr210"}}, "f")
    with pytest.raises(ScenarioError, match=r"f \[scenario\]: missing field 'robot'"):
        _parse_header({"scenario": {"name": "s"}}, "f")
    with pytest.raises(ScenarioError, match=r"\[scenario\]\.seed: expected an integer >= 0"):
        _parse_header({"scenario": {"name": "s", "robot": "kr210", "seed": False}}, "f")


def test_geometric_values_are_param_names_and_sigmas_are_not_negative() -> None:
    geo = _parse_geometric({"geometric": {"d_mm": 0.1, "values": {"theta2": 0.001}, "beta_joints": [2]}}, "f")
    assert (geo.d_mm, geo.a_mm, geo.values, geo.beta_joints) == (0.1, 0.0, {"theta2": 0.001}, (2,))
    with pytest.raises(ScenarioError, match=r"\.values: unknown parameter 'theta9'"):
        _parse_geometric({"geometric": {"values": {"theta9": 0.0}}}, "f")
    with pytest.raises(ScenarioError, match=r"\[geometric\]\.a_mm: must be >= 0"):
        _parse_geometric({"geometric": {"a_mm": -0.1}}, "f")
    with pytest.raises(ScenarioError, match=r"\[geometric\]\.beta_joints: expected a list of joint numbers"):
        _parse_geometric({"geometric": {"beta_joints": [7]}}, "f")


def test_effects_drift_goes_to_the_catalogue_arrays_and_a_step_needs_its_moment() -> None:
    eff = _parse_effects(
        {
            "effects": {
                "drift_mm_per_h": [0.1, 0.2, 0.3],
                "drift_mm_per_h2": [0.0, 0.0, -0.5],
                "step_at_s": 7200.0,
            }
        },
        "f",
    )
    assert eff.drift_y_mm_per_h1 == 0.2 and eff.drift_z_mm_per_h2 == -0.5
    assert eff.step_at == 2.0  # hours
    assert _parse_effects({}, "f").step_at == math.inf
    with pytest.raises(ScenarioError, match="step_deg needs step_at_s"):
        _parse_effects({"effects": {"step_deg": [0.0, 0.01, 0.0, 0.0, 0.0, 0.0]}}, "f")


def test_effects_take_as_many_harmonics_as_the_first_sine_row() -> None:
    sin = [[0.001, 0.002, 0.003]] + [[0.0] * 3] * 5
    eff = _parse_effects({"effects": {"cyclic_sin_deg": sin}}, "f")
    assert eff.n_harmonics == 3
    np.testing.assert_array_equal(eff.cyclic_cos_deg, np.zeros((6, 3)))
    with pytest.raises(ScenarioError, match=r"cyclic_cos_deg: expected shape \(6, 3\)"):
        _parse_effects({"effects": {"cyclic_sin_deg": sin, "cyclic_cos_deg": [[0.0, 0.0]] * 6}}, "f")


def test_noise_motion_and_cell_take_their_defaults_and_refuse_out_of_range() -> None:
    assert _parse_noise({}, "f").tracker_sigma_mm == 0.01
    assert _parse_motion({}, "f").dwell_s == 0.5
    cell = _parse_cell({}, "f")
    assert (cell.grating_joints, cell.grating_radius_mm, cell.temp_start_c) == ((1, 2, 3), 400.0, 20.0)
    with pytest.raises(ScenarioError, match=r"\[noise\]\.joint_repeatability_deg: values must be >= 0"):
        _parse_noise({"noise": {"joint_repeatability_deg": [-1.0] + [0.0] * 5}}, "f")
    with pytest.raises(ScenarioError, match=r"\[motion\]\.servo_time_constant_s: must be >= 1e-06"):
        _parse_motion({"motion": {"servo_time_constant_s": 0.0}}, "f")
    with pytest.raises(ScenarioError, match=r"\[cell\]\.temp_period_h: must be >= 1e-06"):
        _parse_cell({"cell": {"temp_period_h": 0.0}}, "f")


def test_campaign_checks_box_angles_home_payload_fraction_and_counts() -> None:
    cam = _parse_campaign({"campaign": {**BOX, "payload_kg": [0.0, 50.0], "targets": 3}}, "f", KR210)
    assert (cam.payload_kg, cam.targets, cam.repeats, cam.seed, cam.check_fraction) == (
        (0.0, 50.0),
        3,
        1,
        0,
        0.4,
    )
    refusals = [
        ({"box_max_mm": [1.0, 0.0, 1.0]}, "box_max_mm must exceed box_min_mm"),
        ({"abc_min_deg": [1.0, 0.0, 0.0]}, "abc_max_deg must not be below abc_min_deg"),
        ({"home_deg": [0.0, -85.0, 125.0, 0.0, -40.0, 9999.0]}, "home_deg: outside the axis limits"),
        ({"payload_kg": []}, "payload_kg: give at least one payload"),
        ({"check_fraction": 1.0}, "check_fraction: must be below 1"),
        ({"repeats": 0}, r"repeats: expected an integer >= 1"),
        ({"targets": 0}, r"targets: expected an integer >= 1"),
        ({"seed": -1}, r"seed: expected an integer >= 0"),
    ]
    for change, match in refusals:
        with pytest.raises(ScenarioError, match=match):
            _parse_campaign({"campaign": {**BOX, **change}}, "f", KR210)
