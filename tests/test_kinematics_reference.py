"""The KR 210 reference vectors of shared/spec and the presets' agreement with the spec files."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.kinematics.forward import chain, gravity_torques_nm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import load_robot


def _vectors(spec_dir: Path) -> list[dict[str, float]]:
    with (spec_dir / "kr210_fk_vectors.csv").open() as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def test_presets_match_the_spec_files(spec_dir: Path) -> None:
    assert load_robot("kr210").to_dict() == load_robot(spec_dir / "kr210_r2700_extra.toml").to_dict()
    assert load_robot("irb120").to_dict() == load_robot(spec_dir / "abb_irb120.toml").to_dict()


def test_kr210_reference_positions_and_torques(spec_dir: Path) -> None:
    rows = _vectors(spec_dir)
    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    a_deg = np.array([[r[f"a{i}"] for i in range(1, 7)] for r in rows])
    q = axes_deg_to_q_rad(a_deg, robot.sign)
    ch = chain(params, q)
    flange = np.array([[r["flange_x"], r["flange_y"], r["flange_z"]] for r in rows])
    tcp = np.array([[r["tcp_x"], r["tcp_y"], r["tcp_z"]] for r in rows])
    np.testing.assert_allclose(ch.world_T_frame[:, 6, :3, 3], flange, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ch.tcp_mm, tcp, rtol=0, atol=1e-6)
    tau = gravity_torques_nm(params, q, robot.link_mass_kg, robot.link_com_mm, 0.0, ch)
    tau_payload = gravity_torques_nm(params, q, robot.link_mass_kg, robot.link_com_mm, 150.0, ch)
    ref = np.array([[r["tau2_nm"], r["tau3_nm"]] for r in rows])
    ref_payload = np.array([[r["tau2_payload150_nm"], r["tau3_payload150_nm"]] for r in rows])
    np.testing.assert_allclose(tau[:, 1:3], ref, rtol=0, atol=1e-3)
    np.testing.assert_allclose(tau_payload[:, 1:3], ref_payload, rtol=0, atol=1e-3)


def test_cli_fk_reproduces_a_reference_row(spec_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    row = _vectors(spec_dir)[3]
    axes = [str(row[f"a{i}"]) for i in range(1, 7)]
    assert main(["robot", "fk", "kr210", *axes, "--payload-kg", "150"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"flange_mm", "tcp_mm", "gravity_torque_nm"}
    np.testing.assert_allclose(out["tcp_mm"], [row["tcp_x"], row["tcp_y"], row["tcp_z"]], atol=1e-6)
    np.testing.assert_allclose(
        out["gravity_torque_nm"][1:3], [row["tau2_payload150_nm"], row["tau3_payload150_nm"]], atol=1e-3
    )


def test_cli_fk_refuses_axes_outside_limits(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["robot", "fk", "kr210", "0", "-90", "90", "0", "0", "400"]) == 2
    assert "A6=400" in capsys.readouterr().err


def test_gravity_torque_is_minus_the_gradient_of_potential_energy() -> None:
    """Independent check of the torque formula: tau = -dU/dq by central differences."""
    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    rng = np.random.default_rng(3)
    q = rng.uniform(-1.5, 1.5, (5, 6))
    payload = 80.0

    def potential_j(qq: np.ndarray) -> np.ndarray:
        ch = chain(params, qq)
        com = ch.world_T_frame[:, 1:, :3, :3] @ robot.link_com_mm[None, :, :, None]
        z_mm = com[..., 2, 0] + ch.world_T_frame[:, 1:, 2, 3]
        return 9.81 * ((z_mm * robot.link_mass_kg).sum(axis=1) + payload * ch.tcp_mm[:, 2]) / 1000.0

    tau = gravity_torques_nm(params, q, robot.link_mass_kg, robot.link_com_mm, payload)
    h = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        grad = (potential_j(q + dq) - potential_j(q - dq)) / (2 * h)
        np.testing.assert_allclose(tau[:, j], -grad, atol=1e-4)
