"""An honest diagnosis: no noise floor without evidence, structure no effect names, time effects.

Campaigns of the simulated plant (``real-like`` and ``kr210-geometric`` scenarios) with a drift of
the TCP or a step of one joint's zero withheld: the data set has no column that names either (the
temperature is constant, ``t_s`` is plain time). Diagnosed with the vocabulary of diagnose.md alone,
the remainder must follow time (``residual_structure``), no joint effect may be named wrongly, and
without repeats no noise floor is claimed. With ``drift`` / ``step`` in the vocabulary they are
named and the remainder falls to the noise. With repeats the noise floor is within 30 % of the
true one.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from diagnosis_campaigns import PLANT_NOISE_FLOOR_MM

from comp_daemon.diagnosis import DiagnoseOptions, diagnose
from comp_daemon.diagnosis.report import render_report_html
from comp_daemon.models.effects import EffectParams
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.scenario import Scenario, load_scenario

#: the vocabulary of shared/spec/diagnose.md (the catalogue without the time effects)
SPEC_VOCABULARY = ("backlash", "ratio", "cyclic", "compliance", "thermal")
TIME = ("t_s", "pose_order")


def _scenario(name: str, effects: EffectParams, **noise: Any) -> Scenario:
    """The scenario with ``effects``, a constant temperature, one payload and one target.

    One payload: the plant visits the poses in one block per payload, so a second payload would
    change at one moment too and its gravity torques could stand in for a step. One target: the
    noise floor's evidence here is repeats or nothing (not the distances of several reflectors).
    """
    sc = load_scenario(name)
    sc = dataclasses.replace(
        sc, effects=effects, campaign=dataclasses.replace(sc.campaign, payload_kg=(0.0,), targets=1)
    )
    cell = dataclasses.replace(sc.cell, temp_drift_k_per_h=0.0, temp_amplitude_k=0.0)
    sc = dataclasses.replace(sc, cell=cell)
    if noise:
        sc = dataclasses.replace(sc, noise=dataclasses.replace(sc.noise, **noise))
    return sc


def _drift(v_mm_per_h: tuple[float, float, float]) -> EffectParams:
    return EffectParams.zeros(2).with_values(["vx", "vy", "vz"], list(v_mm_per_h))


def _step(joint: int, size_deg: float, at_s: float) -> EffectParams:
    return dataclasses.replace(EffectParams.zeros(2), step_at=at_s / 3600.0).with_values(
        [f"sz{joint}"], [size_deg]
    )


def _time_structure(doc: dict) -> list[dict]:
    return [r for r in doc["residual_structure"] if r["against"] in TIME and r["significant"]]


def _noise_3d(sc: Scenario) -> float:
    return math.sqrt(3.0) * sc.noise.tracker_sigma_mm


def test_withheld_drift_shows_as_time_structure_without_a_noise_floor_then_is_named() -> None:
    sc = _scenario("kr210-geometric", _drift((0.0, 0.0, 0.0)))
    span_h = run_campaign(sc, 200, seed=5, gratings=False).t_s.max() / 3600.0
    # a drift of about eight times the tracker's 3-D noise over the campaign, mostly along z
    v = 8.0 * _noise_3d(sc) / span_h
    sc = _scenario("kr210-geometric", _drift((0.3 * v, -0.2 * v, v)))
    ds = run_campaign(sc, 200, seed=5, gratings=False)
    spec = diagnose(ds, sc.robot, DiagnoseOptions(effects=SPEC_VOCABULARY)).to_json()
    assert spec["noise_floor_mm"] is None and spec["noise_floor_source"] is None
    assert "could not be compared with noise" in spec["where"]["summary"]
    assert _time_structure(spec), spec["residual_structure"]
    assert "follows time" in spec["where"]["summary"]
    # no joint effect stands in for the drift
    assert not any(s["joints"] for s in spec["steps"][1:] if s["significant"]), spec["steps"]
    diag = diagnose(ds, sc.robot, DiagnoseOptions(tracker_sigma_mm=sc.noise.tracker_sigma_mm))
    full = diag.to_json()
    assert full["unmodelled"] == ["drift"], full["steps"]
    page = render_report_html(diag)
    assert "drift contribution" in page and "campaign clock" in page
    assert full["noise_floor_source"] == "declared"
    # the remainder falls to the plant's noise (tracker and joint repeatability, measured from
    # repeats) and shows no time structure
    assert full["unexplained_rms_mm"] < 1.25 * PLANT_NOISE_FLOOR_MM
    assert not _time_structure(full)


def test_withheld_step_shows_as_time_structure_then_is_named_on_its_joint() -> None:
    sc0 = _scenario("kr210-geometric", EffectParams.zeros(2))
    t_end = run_campaign(sc0, 200, seed=6, gratings=False).t_s.max()
    sc = _scenario("kr210-geometric", _step(2, 0.004, 0.55 * t_end))
    ds = run_campaign(sc, 200, seed=6, gratings=False)
    spec = diagnose(ds, sc.robot, DiagnoseOptions(effects=SPEC_VOCABULARY)).to_json()
    assert spec["noise_floor_mm"] is None
    assert _time_structure(spec), spec["residual_structure"]
    assert not any(s["joints"] for s in spec["steps"][1:] if s["significant"]), spec["steps"]
    diag = diagnose(ds, sc.robot)
    full = diag.to_json()
    named = {s["effect"]: s["joints"] for s in full["steps"][1:] if s["significant"]}
    assert named == {"step": [2]}, full["steps"]
    assert "step contribution" in render_report_html(diag)
    step = next(s for s in full["steps"] if s["effect"] == "step")
    assert step["params"]["step_deg"]["2"] == pytest.approx(0.004, rel=0.2)
    # the moment found lies within one search position of the truth
    clock_true_h = (0.55 * t_end - ds.t_s.min()) / 3600.0
    assert abs(step["params"]["step_at"] - clock_true_h) < 0.1 * (ds.t_s.max() - ds.t_s.min()) / 3600.0
    assert not _time_structure(full)


def test_without_times_the_row_order_carries_the_structure() -> None:
    sc = _scenario("real-like", _drift((0.0, 0.0, 0.0)))
    span_h = run_campaign(sc, 250, seed=7, gratings=False).t_s.max() / 3600.0
    v = 10.0 * _noise_3d(sc) / span_h
    sc = _scenario("real-like", _drift((v, 0.5 * v, -0.5 * v)))
    ds = dataclasses.replace(run_campaign(sc, 250, seed=7, gratings=False), t_s=None)
    doc = diagnose(ds, sc.robot, DiagnoseOptions(effects=SPEC_VOCABULARY)).to_json()
    assert [r["against"] for r in _time_structure(doc)] == ["pose_order"]
    assert "order of the measurements" in doc["where"]["summary"]
    assert doc["noise_floor_mm"] is None
    full = diagnose(ds, sc.robot).to_json()
    assert "drift" in full["unmodelled"]


def test_geometric_only_campaign_has_no_structure_and_no_floor_claimed() -> None:
    sc = _scenario("kr210-geometric", EffectParams.zeros(2))
    ds = run_campaign(sc, 200, seed=8, gratings=False)
    doc = diagnose(ds, sc.robot).to_json()
    assert doc["unmodelled"] == []
    assert not any(r["significant"] for r in doc["residual_structure"]), doc["residual_structure"]
    assert doc["noise_floor_mm"] is None
    assert {r["against"] for r in doc["residual_structure"]} >= {"t_s", "a1", "a6", "dir2"}


@pytest.mark.parametrize("sigma_mm", [0.005, 0.02])
def test_noise_floor_from_repeats_is_within_30_percent_of_the_true_noise(sigma_mm: float) -> None:
    # no joint repeatability: the true 3-D noise of a measurement is the tracker's √3·σ
    sc = _scenario(
        "real-like", EffectParams.zeros(2), tracker_sigma_mm=sigma_mm, joint_repeatability_deg=np.zeros(6)
    )
    ds = run_campaign(sc, 120, seed=9, repeats=2, gratings=False)
    doc = diagnose(ds, sc.robot).to_json()
    assert doc["noise_floor_source"] == "repeats"
    assert doc["noise_floor_mm"] == pytest.approx(math.sqrt(3.0) * sigma_mm, rel=0.3)
