"""Grating calibration (seed 000 step 1): recovery of a known count → angle map, artifacts, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.daemon.gratings import approach_points
from comp_daemon.rt.grating_cal import (
    GratingCalibration,
    GratingCalibrationError,
    build_calibration,
    fit_joint_map,
    load_calibration,
    load_latest_calibration,
    nominal_slope_deg_per_count,
    save_calibration,
)

RADIUS_MM = 420.0
RES_NM = 50.0


def synthetic(
    scale: float, zero_deg: float, axis_deg: np.ndarray, *, backlash_deg: float = 0.0
) -> np.ndarray:
    """Counts a scale would read at these axis values; each pose approached from both sides."""
    slope = scale * nominal_slope_deg_per_count(RADIUS_MM, RES_NM)
    side = np.where(np.arange(axis_deg.size) % 2 == 0, 0.5, -0.5)
    true_angle = axis_deg + side * backlash_deg  # the joint lags the motor by half the backlash
    return np.round((true_angle - zero_deg) / slope)


@pytest.mark.parametrize(("scale", "zero"), [(1.0031, 12.25), (-0.9987, -33.5), (1.0, 0.0)])
def test_recovers_a_known_map(scale: float, zero: float) -> None:
    axis = np.linspace(-60.0, 75.0, 16)
    counts = synthetic(scale, zero, axis)
    m = fit_joint_map(2, counts, axis, radius_mm=RADIUS_MM, resolution_nm=RES_NM)
    assert m.scale == pytest.approx(scale, rel=1e-6)
    assert m.zero_deg == pytest.approx(zero, abs=1e-5)
    # counts are integers: the map is exact to the count quantisation (50 nm on 420 mm ≈ 7e-6 deg)
    assert m.residual_max_deg <= abs(m.slope_deg_per_count)
    assert m.angle_deg(counts[3]) == pytest.approx(axis[3], abs=1e-5)
    assert m.n_readings == 16 and m.span_deg == pytest.approx(135.0)


def test_two_sided_approach_averages_backlash_out_of_the_zero() -> None:
    axis = np.repeat(np.linspace(-40.0, 40.0, 9), 2)
    counts = synthetic(1.002, 5.0, axis, backlash_deg=0.01)
    m = fit_joint_map(1, counts, axis, radius_mm=RADIUS_MM)
    assert m.zero_deg == pytest.approx(5.0, abs=2e-4)
    assert m.scale == pytest.approx(1.002, rel=1e-5)
    assert m.residual_rms_deg == pytest.approx(0.005, rel=0.02)  # half the backlash stays visible


def test_refusals_name_the_problem() -> None:
    axis = np.linspace(-30.0, 30.0, 10)
    counts = synthetic(1.0, 0.0, axis)
    with pytest.raises(GratingCalibrationError, match="A3: 4 readings, at least 6"):
        fit_joint_map(3, counts[:4], axis[:4], radius_mm=RADIUS_MM)
    with pytest.raises(GratingCalibrationError, match=r"span 2\.000 deg"):
        narrow = np.linspace(0.0, 2.0, 10)
        fit_joint_map(1, synthetic(1.0, 0.0, narrow), narrow, radius_mm=RADIUS_MM)
    with pytest.raises(GratingCalibrationError, match="wrong radius or wrong joint"):
        fit_joint_map(1, counts, axis, radius_mm=RADIUS_MM * 1.2)
    bad = axis.copy()
    bad[7] = np.nan
    with pytest.raises(GratingCalibrationError, match="reading 7 is not finite"):
        fit_joint_map(1, counts, bad, radius_mm=RADIUS_MM)
    with pytest.raises(GratingCalibrationError, match="10 counts but 9 axis values"):
        fit_joint_map(1, counts, axis[:9], radius_mm=RADIUS_MM)


def _calibration(tmp_path: Path) -> GratingCalibration:
    axis = np.linspace(-50.0, 50.0, 12)
    maps = [
        fit_joint_map(j, synthetic(1.0 + 0.001 * j, 3.0 * j, axis), axis, radius_mm=RADIUS_MM)
        for j in (3, 1, 2)
    ]
    return build_calibration(tmp_path, maps, "2026-11-21T12:00:00Z")


def test_artifact_round_trip_is_bit_exact_and_versions_grow(tmp_path: Path) -> None:
    cal = _calibration(tmp_path)
    assert cal.version == 1 and [m.joint for m in cal.joints] == [1, 2, 3]
    path = save_calibration(tmp_path, cal)
    assert path.name == "grating-cal-v0001.json"
    back = load_calibration(path)
    assert back == cal  # every float bit-exact
    with pytest.raises(GratingCalibrationError, match="never overwritten"):
        save_calibration(tmp_path, cal)
    cal2 = _calibration(tmp_path)
    assert cal2.version == 2
    save_calibration(tmp_path, cal2)
    latest = load_latest_calibration(tmp_path)
    assert latest is not None and latest.version == 2
    assert load_latest_calibration(tmp_path / "nothing-here") is None
    assert list(tmp_path.glob(".grating-cal-*")) == []  # no temporary files left behind


def test_bad_artifacts_are_refused_by_field(tmp_path: Path) -> None:
    cal = _calibration(tmp_path)
    doc = cal.to_dict()
    with pytest.raises(GratingCalibrationError, match="'kind'"):
        GratingCalibration.from_dict({**doc, "kind": "model"})
    broken = json.loads(json.dumps(doc))
    del broken["joints"][1]["zero_deg"]
    with pytest.raises(GratingCalibrationError, match=r"joints\[1\]: missing field 'zero_deg'"):
        GratingCalibration.from_dict(broken)
    twice = json.loads(json.dumps(doc))
    twice["joints"][1]["joint"] = 1
    with pytest.raises(GratingCalibrationError, match="lists a joint twice"):
        GratingCalibration.from_dict(twice)
    p = tmp_path / "grating-cal-v0009.json"
    p.write_text("{not json", encoding="utf-8")
    with pytest.raises(GratingCalibrationError, match="not JSON"):
        load_calibration(p)
    with pytest.raises(KeyError, match="A5"):
        cal.for_joint(5)


def test_each_pose_is_approached_from_below_and_above_on_the_grating_joints_only() -> None:
    pose = np.array([10.0, -20.0, 30.0, 0.0, 45.0, -5.0])
    below, above = approach_points(pose, (2, 3), 0.5)
    np.testing.assert_array_equal(below, [10.0, -20.5, 29.5, 0.0, 45.0, -5.0])
    np.testing.assert_array_equal(above, [10.0, -19.5, 30.5, 0.0, 45.0, -5.0])
    assert pose.tolist() == [10.0, -20.0, 30.0, 0.0, 45.0, -5.0]  # the pose itself is left alone
