"""Blind tests of the diagnosis: campaigns with effects withheld from the twin must be named.

Two independent sources of campaigns: ``diagnosis_campaigns`` (nominal + random geometry + chosen
effects through the effect model, tracker noise σ 0.01 mm, wide pose boxes) and the simulated plant
of ``comp_daemon.sim`` (PTP motion, play operator, joint repeatability, seed 000's drilling box)
with the scenario's effects replaced by the withheld ones. The diagnosis sees only the data set and
the nominal robot. This is a representative subset; ``benchmarks/blind_diagnosis.py`` runs the grid.
"""

from __future__ import annotations

import pytest
from diagnosis_campaigns import NOISE_FLOOR_MM, PLANT_NOISE_FLOOR_MM, make_campaign, plant_campaign

from comp_daemon.diagnosis import diagnose
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.scenario import load_scenario

NEAR, LARGE = 1.0 * NOISE_FLOOR_MM, 10.0 * NOISE_FLOOR_MM


def named(doc: dict) -> dict[str, list[int]]:
    return {s["effect"]: s["joints"] for s in doc["steps"][1:] if s["significant"]}


SINGLE = [
    # (robot, effect, joint, size, seed, tracker frame)
    ("kr210", "backlash", 2, NEAR, 11, False),
    ("kr210", "backlash", 5, LARGE, 12, True),
    ("kr210", "ratio", 1, NEAR, 13, False),
    ("kr210", "ratio", 3, LARGE, 14, False),
    ("kr210", "cyclic", 2, NEAR, 15, True),
    ("kr210", "cyclic", 5, LARGE, 16, False),
    ("kr210", "compliance", 2, LARGE, 17, False),
    ("kr210", "compliance", 3, NEAR, 18, False),
    ("kr210", "thermal", None, NEAR, 19, True),
    ("irb120", "backlash", 1, LARGE, 21, False),
    ("irb120", "ratio", 5, NEAR, 22, True),
    ("irb120", "cyclic", 4, NEAR, 23, False),
    ("irb120", "compliance", 2, NEAR, 24, False),
    ("irb120", "thermal", None, LARGE, 25, False),
]


@pytest.mark.parametrize(("robot", "effect", "joint", "size", "seed", "tracker"), SINGLE)
def test_one_withheld_effect_is_named_with_its_joint(robot, effect, joint, size, seed, tracker) -> None:
    camp = make_campaign(robot, seed, [(effect, joint, size)], tracker=tracker)
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert doc["unmodelled"] == [effect]
    assert named(doc) == {effect: [] if joint is None else [joint]}
    assert doc["frame"]["measured_in"] == ("tracker" if tracker else "base")
    # the remainder is at the noise floor once the effect is in
    assert doc["unexplained_rms_mm"] < 1.3 * doc["noise_floor_mm"]


@pytest.mark.parametrize(
    ("robot", "seed", "tracker", "joint_noise_deg"),
    [
        ("kr210", 31, False, 0.0),
        ("kr210", 32, True, 0.002),
        ("irb120", 36, False, 0.0),
        ("irb120", 34, True, 0.002),
        ("kr210", 35, False, 0.002),
    ],
)
def test_geometric_only_campaign_has_nothing_unmodelled(robot, seed, tracker, joint_noise_deg) -> None:
    camp = make_campaign(robot, seed, [], tracker=tracker, joint_noise_deg=joint_noise_deg)
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert doc["unmodelled"] == []
    assert doc["joints"] == []
    assert doc["steps"][0]["effect"] == "geometric" and doc["steps"][0]["significant"]
    assert all(not s["significant"] for s in doc["steps"][1:])


@pytest.mark.parametrize(
    ("pair", "size", "seed"),
    [
        ((("backlash", 2), ("compliance", 3)), NEAR, 41),
        ((("ratio", 1), ("thermal", None)), LARGE, 42),
        ((("cyclic", 3), ("backlash", 1)), NEAR, 43),
    ],
)
def test_two_withheld_effects_are_both_named(pair, size, seed) -> None:
    camp = make_campaign("kr210", seed, [(e, j, size) for e, j in pair])
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert named(doc) == {e: [] if j is None else [j] for e, j in pair}
    assert sorted(doc["unmodelled"]) == sorted(e for e, _ in pair)


# ---- the simulated plant ---------------------------------------------------------------------------
def test_plant_geometric_only_scenario_has_nothing_unmodelled() -> None:
    sc = load_scenario("kr210-geometric")
    for tracker in (False, True):
        ds = run_campaign(sc, 150, seed=7, repeats=2, in_tracker_frame=tracker)
        doc = diagnose(ds, sc.robot).to_json()
        assert doc["unmodelled"] == [], doc["selection"]
        assert doc["noise_floor_source"] == "repeats"
        assert doc["noise_floor_mm"] == pytest.approx(PLANT_NOISE_FLOOR_MM, rel=0.25)


@pytest.mark.parametrize(
    ("withheld", "size", "wide", "tracker", "seed"),
    [
        ([("backlash", 2)], 1.0, False, False, 81),
        ([("compliance", 3)], 5.0, True, True, 82),
        ([("ratio", 1)], 5.0, True, False, 83),
        ([("thermal", None)], 1.0, False, False, 84),
        ([("backlash", 1), ("cyclic", 3)], 5.0, True, False, 85),
    ],
    ids=[
        "backlash-J2-drilling-box",
        "compliance-J3-tracker",
        "ratio-J1",
        "thermal-drilling-box",
        "backlash-J1+cyclic-J3",
    ],
)
def test_plant_campaign_with_withheld_effects(withheld, size, wide, tracker, seed) -> None:
    camp = plant_campaign(
        [(e, j, size * PLANT_NOISE_FLOOR_MM) for e, j in withheld], seed, wide=wide, tracker=tracker
    )
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert named(doc) == {e: [] if j is None else [j] for e, j in withheld}, doc["selection"]
