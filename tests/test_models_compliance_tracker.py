"""Seed 004's compliance-aware zero-offset calibration from tracker positions (our data sets)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.seed004_compliance import (
    SEED004_COMPLIANCE_RAD_PER_NM,
    SEED004_TRACKER_AXES_DEG,
    SEED004_ZERO_OFFSETS_DEG,
    reproduce_seed004_tracker,
)
from comp_daemon.kinematics.forward import gravity_torques_nm
from comp_daemon.kinematics.inverse import rotation_kuka_abc_deg
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.compliance import ComplianceModel, calibrate_compliance
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")
OFFSETS = np.deg2rad(SEED004_ZERO_OFFSETS_DEG)
COMP = np.array(SEED004_COMPLIANCE_RAD_PER_NM)


def _axes(n: int, seed: int) -> np.ndarray:
    box = np.array(SEED004_TRACKER_AXES_DEG)
    return box[:, 0] + np.random.default_rng(seed).random((n, 6)) * (box[:, 1] - box[:, 0])


def test_model_is_the_effects_twin_with_offsets_and_compliance() -> None:
    model = ComplianceModel(ROBOT, OFFSETS, COMP)
    a = _axes(20, 0)
    payload = np.linspace(0.0, 3.0, 20)
    dx = np.zeros(N_PARAMS)
    dx[0:30:5] = OFFSETS
    twin = twin_tcp_mm(
        ROBOT,
        KinematicParams.from_robot(ROBOT).apply(dx),
        EffectParams(compliance_rad_per_nm=COMP),
        a,
        None,
        payload,
    )
    np.testing.assert_array_equal(model.predict_tcp_mm(a, None, payload), twin)
    # δθ = C·τ with the gravity torques of the links and the payload (joints 2 and 3 only)
    tau = gravity_torques_nm(
        model.params, axes_deg_to_q_rad(a, model.params.sign), ROBOT.link_mass_kg, ROBOT.link_com_mm, payload
    )
    np.testing.assert_allclose(model.deflection_rad(a, payload), COMP * tau, rtol=1e-12)
    assert np.all(model.deflection_rad(a, payload)[:, [0, 3, 4, 5]] == 0.0)


def test_noise_free_positions_recover_offsets_and_compliance() -> None:
    truth = ComplianceModel(ROBOT, OFFSETS, COMP)
    a = _axes(60, 1)
    payload = np.where(np.arange(60) % 2 == 0, 0.0, 3.0)
    p = truth.predict_tcp_mm(a, None, payload)
    fit = calibrate_compliance(ROBOT, a, p, payload_kg=payload, frame="base")
    # the TCP sits on axis 6 (tool at the flange centre): its zero offset does not move the TCP
    assert fit.report.removed_names() == ("theta6",)
    assert fit.frame == "base"
    np.testing.assert_allclose(fit.model.zero_offset_rad[:5], OFFSETS[:5], atol=1e-10)
    np.testing.assert_allclose(fit.model.compliance_rad_per_nm, COMP, rtol=1e-7, atol=1e-14)
    assert fit.rms_mm < 1e-8
    original = calibrate_compliance(ROBOT, a, p, payload_kg=payload, frame="base", compliance_joints=())
    assert np.all(original.model.compliance_rad_per_nm == 0.0)
    assert original.rms_mm > 0.05  # the deflection the original model cannot express


def test_tracker_frame_is_registered_and_theta1_goes_with_the_base_rotation() -> None:
    truth = ComplianceModel(ROBOT, OFFSETS, COMP)
    a = _axes(60, 2)
    world_T_base = np.eye(4)
    world_T_base[:3, :3] = rotation_kuka_abc_deg(np.array([[30.0, 1.0, -2.0]]))[0]
    world_T_base[:3, 3] = [2500.0, -800.0, 300.0]
    p_base = truth.predict_tcp_mm(a)
    p = p_base @ world_T_base[:3, :3].T + world_T_base[:3, 3]
    fit = calibrate_compliance(ROBOT, a, p)
    assert fit.frame == "tracker"
    assert "theta1" in fit.report.removed_names()
    np.testing.assert_allclose(fit.model.compliance_rad_per_nm, COMP, rtol=1e-6, atol=1e-13)
    np.testing.assert_allclose(fit.model.zero_offset_rad[1:5], OFFSETS[1:5], atol=1e-9)
    assert fit.rms_mm < 1e-7
    np.testing.assert_allclose(fit.model.predict_tcp_mm(a[:5]), p[:5], atol=1e-6)


def test_tracker_reproduction_compliance_reaches_the_noise_floor() -> None:
    result = reproduce_seed004_tracker(seed=0, n_poses=160, n_fit=80)
    assert result.compliance_mm < 0.03  # tracker σ 0.01 mm per axis
    assert result.zero_offset_mm > 5.0 * result.compliance_mm
    assert result.uncompensated_mm > 1.0
    assert result.table()["rows"] == {"fit": 80, "check": 80}


def test_payload_round_trip_is_bit_exact() -> None:
    model = ComplianceModel(ROBOT, OFFSETS * 0.37, COMP * 1.1, tool_xyz_mm=[1.0, 2.0, 3.0])
    stored = json.loads(json.dumps(model.to_payload()))
    again = ComplianceModel.from_payload(ROBOT, stored, None, np.eye(4))
    a = _axes(10, 3)
    np.testing.assert_array_equal(again.predict_tcp_mm(a, None, 2.0), model.predict_tcp_mm(a, None, 2.0))
    del stored["compliance_rad_per_nm"]
    with pytest.raises(ValueError, match="missing field 'compliance_rad_per_nm'"):
        ComplianceModel.from_payload(ROBOT, stored, None, np.eye(4))


def test_bad_input_is_refused_by_name() -> None:
    a = _axes(10, 4)
    with pytest.raises(ValueError, match=r"measured positions must have shape \(10, 3\)"):
        calibrate_compliance(ROBOT, a, np.zeros((9, 3)))
    with pytest.raises(ValueError, match="offset_joints: joint listed twice"):
        calibrate_compliance(ROBOT, a, np.zeros((10, 3)), offset_joints=(1, 1))
    with pytest.raises(ValueError, match="compliance_rad_per_nm: expected shape"):
        ComplianceModel(ROBOT, OFFSETS, COMP[:3])
    with pytest.raises(ValueError, match="zero_offset_rad: values must be finite"):
        ComplianceModel(ROBOT, [np.nan] * 6, COMP)
