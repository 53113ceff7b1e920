"""With several reflectors per pose the ladder fits and tests every one: a wrist error the TCP cannot
show (the TCP on axis 6) is found through the further reflectors."""

from __future__ import annotations

import numpy as np
from diagnosis_campaigns import wrist_campaign

from comp_daemon.diagnosis import diagnose


def test_a_joint6_backlash_is_found_through_the_further_reflectors() -> None:
    camp = wrist_campaign(5, 0.03)
    assert np.allclose(camp.robot.tool_xyz_mm[:2], 0.0), "the TCP must lie on axis 6 for this test"
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert "backlash" in doc["unmodelled"]
    backlash = next(s for s in doc["steps"] if s["effect"] == "backlash" and s["significant"])
    assert 6 in backlash["joints"]
    assert abs(backlash["params"]["h_deg"]["6"] - 0.03) < 0.005
    reasons = [s["reason"] for s in doc["skipped"] if s["effect"] == "backlash"]
    assert not any("does not move the TCP" in r for r in reasons)


def test_without_a_wrist_error_the_further_reflectors_name_nothing() -> None:
    camp = wrist_campaign(6, 0.0)
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert doc["unmodelled"] == []
