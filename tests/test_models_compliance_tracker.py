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
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.compliance import ComplianceModel, _geometric_unknowns, calibrate_compliance
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


def test_torques_are_the_papers_planar_closed_forms_and_the_arm_sags_under_them() -> None:
    """Seed 004 eqs 3–4 in the arm's plane (A1 = A4 = A5 = A6 = 0), term by term.

    With the upper arm at A2 from vertical (θ2 = 90° − A2 from horizontal, as in the paper's
    figure): τ3 = G3·L2·cos(θ2 + θ3) depends on A2 + A3 only, and τ2 − τ3 = (G2·L1 + G3·L3)·cos θ2
    with G2·L1 = m2·g·|com2|, G3 the weight of links 3–6 and the payload, L3 = a2. δθ = C·τ in rad
    for C in rad/(N m) and τ in N m: a forward-leaning arm (A2 > 0) is pulled further forward.
    """
    g = 9.81
    a2 = np.linspace(-40.0, 60.0, 11)
    a3 = np.linspace(30.0, -50.0, 11)
    payload = 2.0
    a = np.zeros((11, 6))
    a[:, 1], a[:, 2] = a2, a3
    model = ComplianceModel(ROBOT, np.zeros(6), COMP)
    tau = gravity_torques_nm(
        model.params, axes_deg_to_q_rad(a, model.params.sign), ROBOT.link_mass_kg, ROBOT.link_com_mm, payload
    )
    # τ3 depends on the forearm's angle A2 + A3 alone
    same_forearm = a.copy()
    same_forearm[:, 1], same_forearm[:, 2] = 0.0, a2 + a3
    tau_same = gravity_torques_nm(
        model.params,
        axes_deg_to_q_rad(same_forearm, model.params.sign),
        ROBOT.link_mass_kg,
        ROBOT.link_com_mm,
        payload,
    )
    np.testing.assert_allclose(tau[:, 2], tau_same[:, 2], atol=1e-9)
    g2_l1 = ROBOT.link_mass_kg[1] * g * np.linalg.norm(ROBOT.link_com_mm[1]) / 1000.0
    g3 = (ROBOT.link_mass_kg[2:].sum() + payload) * g
    l3 = KinematicParams.from_robot(ROBOT).a_mm[1] / 1000.0
    cos_theta2 = np.cos(np.deg2rad(90.0 - a2))
    np.testing.assert_allclose(tau[:, 1] - tau[:, 2], (g2_l1 + g3 * l3) * cos_theta2, atol=1e-9)
    # the deflection follows the torque: C > 0 in our (DH) torque sign, rad = rad/(N m) · N m
    defl = model.deflection_rad(a, payload)
    np.testing.assert_allclose(defl[:, 1:3], COMP[1:3] * tau[:, 1:3], rtol=1e-12)
    lean = a[a2 > 10.0]
    stiff = ComplianceModel(ROBOT, np.zeros(6), np.zeros(6))
    dx = model.predict_tcp_mm(lean, None, payload) - stiff.predict_tcp_mm(lean, None, payload)
    assert np.all(dx[:, 2] < 0.0)  # the TCP sags


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
    world_T_base[:3, :3] = abc_deg_to_matrix(np.array([30.0, 1.0, -2.0]))
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


def test_geometric_unknowns_beside_the_compliance() -> None:
    base = ["base_x", "base_y", "base_z", "base_rx", "base_ry", "base_rz"]
    assert _geometric_unknowns((2, 3), tracker=False, fit_tool=False, geometry=False) == ["theta2", "theta3"]
    # a tracker frame's registration is refined with the offsets; the tool after them
    assert _geometric_unknowns((1,), tracker=True, fit_tool=True, geometry=False) == [
        *base,
        "theta1",
        "tool_x",
        "tool_y",
        "tool_z",
    ]
    assert _geometric_unknowns((1,), tracker=True, fit_tool=False, geometry=True) == list(PARAM_NAMES)
