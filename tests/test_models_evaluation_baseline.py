"""evaluate's honest baseline and extrapolation: the nominal robot with its base and targets
registered (6 + 3 per target) beside the raw nominal row, and the check rows outside the fitted
axis ranges counted per model in the table."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, write_dataset
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.evaluation import (
    REGISTERED_NOMINAL,
    error_statistics,
    format_table2,
    outside_fit_ranges,
    registered_nominal,
)
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")
FLANGE_TARGETS_MM = np.array([[140.0, 30.0, 260.0], [-20.0, 90.0, 300.0], [30.0, -110.0, 280.0]])


def _tracker() -> np.ndarray:
    t = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    t[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = [3200.0, -1400.0, -600.0]
    return t


def _axes(n: int, seed: int) -> np.ndarray:
    mid = KR.axis_limits_deg.mean(axis=1)
    return mid + np.random.default_rng(seed).uniform(-35, 35, (n, 6))


def _measured(a: np.ndarray, seed: int, geometric_error: float = 0.0) -> np.ndarray:
    """(n, 3, 3) three reflectors at FLANGE_TARGETS_MM (not the robot file's tool) measured in a
    tracker frame with 0.005 mm noise, on a robot with ``geometric_error`` (rad, mm) per parameter."""
    rng = np.random.default_rng(seed)
    dx = rng.normal(size=N_PARAMS) * geometric_error
    truth = KinematicParams.from_robot(KR).apply(dx)
    truth = truth.apply(np.r_[np.zeros(36), FLANGE_TARGETS_MM[0] - truth.tool_xyz_mm]).with_base(_tracker())
    model = KinematicModel(KR, truth, None, _tracker(), FLANGE_TARGETS_MM[1:])
    return model.predict_targets_mm(a) + rng.normal(size=(len(a), 3, 3)) * 0.005


def _campaign(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    a = _axes(n, seed)
    return a, _measured(a, seed)


def test_registered_nominal_takes_out_the_unknown_targets() -> None:
    a, pts = _campaign(60, 0)
    model, info = registered_nominal(KR, a, pts[:, 0], pts[:, 1:])
    assert info["parameters"] == 6 + 3 * 3
    assert info["rms_mm"] < 0.01  # the robot is nominal: only the noise is left
    assert np.allclose(info["tool_mm"], FLANGE_TARGETS_MM[0], atol=0.05)
    assert np.allclose(info["targets_mm"], FLANGE_TARGETS_MM[1:], atol=0.05)
    a2, pts2 = _campaign(30, 1)
    registered = error_statistics(pts2[:, 0], model.predict_tcp_mm(a2))["3d"]["rms"]
    raw = KinematicModel(KR, KinematicParams.from_robot(KR).with_base(_tracker()), None, _tracker())
    raw_rms = error_statistics(pts2[:, 0], raw.predict_tcp_mm(a2))["3d"]["rms"]
    assert registered < 0.02 and raw_rms > 100.0


def test_outside_fit_ranges_counts_rows_and_axes() -> None:
    fit = np.zeros((4, 6))
    fit[:, 0] = [-10, 0, 5, 10]
    fit[:, 2] = [0, 1, 2, 3]
    check = np.zeros((3, 6))
    check[0, 0] = 11.0  # A1 above
    check[1, [0, 2]] = [-11.0, 4.0]  # A1 below and A3 above: one row
    assert outside_fit_ranges(fit, check) == {"rows": 2, "per_axis": {"A1": 2, "A3": 1}}
    stats = error_statistics(np.ones((3, 3)), np.zeros((3, 3)))
    text = format_table2(
        {"a": stats, "b": stats},
        {"a": {"fit_s": 0.1, "predict_s": 0.001}, "b": {"fit_s": 0.0, "predict_s": 0.0}},
        {"a": 2},
    )
    lines = text.splitlines()
    assert lines[0].endswith("outside") and lines[2].endswith("|       2") and lines[3].endswith("|       -")


def test_evaluate_prints_both_nominal_rows_and_the_extrapolation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a = _axes(90, 2)
    split = np.where(np.arange(90) % 3 == 0, "check", "fit")
    fit, check = split == "fit", split == "check"
    a[check] = np.clip(a[check], a[fit].min(axis=0), a[fit].max(axis=0))
    a[np.flatnonzero(check)[:4], 0] = a[fit, 0].max() + 5.0  # 4 check rows beyond A1's fitted range
    pts = _measured(a, 2, geometric_error=2e-4)
    data = tmp_path / "three.csv"
    write_dataset(Dataset(a_deg=a, xyz_mm=pts[:, 0], more_xyz_mm=pts[:, 1:], split=split), data)
    out = tmp_path / "eval.json"
    args = ["evaluate", str(data), "--robot", "kr210", "--models", "nominal,kinematic", "--json", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    rows = {line.split("  ")[0]: line for line in text.splitlines() if "|" in line}
    assert REGISTERED_NOMINAL in rows and "nominal" in rows
    doc = json.loads(out.read_text())
    raw = doc["table2"]["nominal"]["3d"]["rms"]
    registered = doc["table2"][REGISTERED_NOMINAL]["3d"]["rms"]
    assert raw > 50.0 and registered < 2.0  # the unknown targets are out of the baseline
    assert doc["fits"][REGISTERED_NOMINAL]["parameters"] == 15
    line = next(x for x in text.splitlines() if x.startswith("extrapolation:"))
    assert line.startswith("extrapolation: 4 of 30 check rows lie outside the fit rows' axis ranges (A1 4)")
    assert doc["fits"]["kinematic"]["check_rows_outside_range"] == 4
    # the kinematic fit names its near-dependent pairs, none inside the tracker's frame alone
    pairs = doc["fits"]["kinematic"]["identifiability"]["near_dependent"]
    assert all(abs(p["correlation"]) > 0.9 for p in pairs)
    assert not any(all(n.startswith("base_") for n in p["pair"]) for p in pairs)
    assert rows["kinematic"].rstrip().endswith("|       4") and rows["nominal"].rstrip().endswith("|       -")
