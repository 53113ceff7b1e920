"""Tracker stations and 6-DOF probes through the preparation, evaluate, the diagnosis and its floor."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from diagnosis_campaigns import NOISE_FLOOR_MM, make_campaign

from comp_daemon.cli import main
from comp_daemon.data.dataset import read_dataset_file, write_dataset
from comp_daemon.diagnosis import diagnose
from comp_daemon.diagnosis.ladder import _noise_floor
from comp_daemon.kinematics.so3 import matrix_to_quat, quat_to_matrix, rotvec_to_matrix
from comp_daemon.models.fitting import FitOptions
from comp_daemon.models.observations import orientation_weight, probe_axis_points_mm
from comp_daemon.models.registry import fit_spec, parse_model_name
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.preparation.campaign import CampaignError, prepare_campaign
from comp_daemon.robot.description import load_robot
from comp_daemon.sim.scenario import load_scenario

TRACKER_SIGMA_MM = load_scenario("kr210-geometric").noise.tracker_sigma_mm


@pytest.fixture(scope="module")
def two_stations(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The simulated cell's geometric KR 210, measured with a 6-DOF probe from two stations."""
    out = tmp_path_factory.mktemp("stations") / "two.csv"
    argv = ["sim", "sample", "--scenario", "kr210-geometric", "--n", "160", "--seed", "7", "--tracker-frame"]
    assert main([*argv, "--restation", "--probe-sigma-deg", "0.01", "--out", str(out)]) == 0
    return out


def _check_rms(path: Path, model: str = "kinematic") -> tuple[float, object]:
    robot = load_robot("kr210")
    prepared = prepare_campaign(read_dataset_file(path), robot)
    fitted = fit_spec(parse_model_name(model), robot, prepared.rows(prepared.fit_rows), FitOptions("tracker"))
    err = prepared.rows(prepared.check_rows).errors(fitted.model)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), prepared


def test_sim_sample_moves_the_tracker_and_measures_the_probe(two_stations: Path) -> None:
    ds = read_dataset_file(two_stations)
    assert ds.station is not None and set(ds.station) == {"A", "B"}
    assert ds.probe_q_wxyz is not None and ds.sigma_mm is not None
    assert np.allclose(ds.sigma_mm, TRACKER_SIGMA_MM)
    assert np.allclose(np.linalg.norm(ds.probe_q_wxyz, axis=1), 1.0)


def test_the_probe_turns_with_its_station(two_stations: Path) -> None:
    """Station B's frame is A's turned 50° about the vertical: the preparation finds it from the
    positions, and the probe's orientations, mapped with it, agree between the stations."""
    _, prepared = _check_rms(two_stations)
    stations = prepared.stations.to_json()["stations"]  # type: ignore[attr-defined]
    moved = [s for s in stations.values() if s["registration"] == "joint"]
    assert len(moved) == 1 and moved[0]["angle_deg"] == pytest.approx(50.0, abs=0.05)
    ds = prepared.dataset  # type: ignore[attr-defined]
    fit = fit_spec(parse_model_name("kinematic"), load_robot("kr210"), prepared.rows(prepared.fit_rows))  # type: ignore[attr-defined]
    assert fit.info["orientation"]["rms_deg"] < 0.05  # both stations' orientations in one frame
    assert quat_to_matrix(ds.probe_q_wxyz).shape == (len(ds), 3, 3)


def test_two_stations_give_a_check_error_near_the_noise(two_stations: Path) -> None:
    rms, prepared = _check_rms(two_stations)
    assert prepared.stations is not None  # type: ignore[attr-defined]
    assert rms < 3.0 * np.sqrt(3.0) * TRACKER_SIGMA_MM
    assert "registered jointly" in prepared.stations.note  # type: ignore[attr-defined]


def test_one_frame_for_two_stations_is_refused_with_the_station_named(
    two_stations: Path, tmp_path: Path
) -> None:
    ds = read_dataset_file(two_stations)
    one = tmp_path / "one.csv"
    write_dataset(dataclasses.replace(ds, station=None), one)
    with pytest.raises(CampaignError, match="station column"):
        prepare_campaign(read_dataset_file(one), load_robot("kr210"))


def test_a_station_with_check_rows_only_is_registered_on_its_own_rows(
    two_stations: Path, tmp_path: Path
) -> None:
    ds = read_dataset_file(two_stations)
    assert ds.station is not None and ds.split is not None
    split = np.where(np.asarray(ds.station) == "B", "check", np.asarray(ds.split))
    only = tmp_path / "b_check_only.csv"
    write_dataset(dataclasses.replace(ds, split=split), only)
    rms, prepared = _check_rms(only)
    stations = prepared.stations.to_json()["stations"]  # type: ignore[attr-defined]
    assert stations["B"]["registration"] == "own rows" and stations["B"]["parameters"] == 6
    assert stations["B"]["fit_rows"] == 0
    assert "registered on its own" in prepared.stations.note  # type: ignore[attr-defined]
    assert rms < 3.0 * np.sqrt(3.0) * TRACKER_SIGMA_MM


def test_evaluate_names_a_station_whose_frame_changed(two_stations: Path, tmp_path: Path, capsys) -> None:
    ds = read_dataset_file(two_stations)
    assert ds.station is not None and ds.split is not None and ds.xyz_mm is not None
    bumped = (np.asarray(ds.station) == "B") & (np.asarray(ds.split) == "check")
    xyz = np.array(ds.xyz_mm)
    # the tracker of station B was knocked after its fit rows were measured: 0.05° and 0.8 mm
    xyz[bumped] = xyz[bumped] @ rotvec_to_matrix(np.array([0.0, 0.0, np.radians(0.05)])).T + [0.8, -0.3, 0.2]
    path = tmp_path / "bumped.csv"
    write_dataset(dataclasses.replace(ds, xyz_mm=xyz), path)
    out_json = tmp_path / "eval.json"
    assert (
        main(["evaluate", str(path), "--robot", "kr210", "--models", "kinematic", "--json", str(out_json)])
        == 0
    )
    out = capsys.readouterr().out
    assert "station B's frame changed" in out and "station A's frame changed" not in out
    doc = json.loads(out_json.read_text())
    assert doc["check_by_station"]["stations"]["B"]["frame_changed"] is True
    assert doc["check_by_station"]["stations"]["A"]["frame_changed"] is False
    assert doc["stations"]["reference"] in ("A", "B")


def test_diagnosis_names_the_station_whose_frame_changed() -> None:
    camp = make_campaign("kr210", 61, [("ratio", 2, 5 * NOISE_FLOOR_MM)])
    ds = camp.dataset
    n = len(ds)
    station = np.where(np.arange(n) < n // 2, "A", "B")
    xyz = np.array(ds.xyz_mm)
    b = station == "B"
    # station B: the tracker re-stationed 50° about the vertical and 5 m away
    xyz[b] = xyz[b] @ rotvec_to_matrix(np.array([0.0, 0.0, np.radians(50.0)])).T + [3000.0, 4000.0, 0.0]
    # and knocked after its fit rows: 0.05° and 0.8 mm on its check rows
    knocked = b & np.isin(np.arange(n), ds.check_rows())
    xyz[knocked] = xyz[knocked] @ rotvec_to_matrix(np.array([0.0, 0.0, np.radians(0.05)])).T + [
        0.8,
        -0.3,
        0.2,
    ]
    doc = diagnose(dataclasses.replace(ds, xyz_mm=xyz, station=tuple(station)), camp.robot).to_json()
    agreement = doc["fit_check_agreement"]
    assert agreement["agree"] is False
    assert any("station B's frame changed" in d for d in agreement["differences"])
    assert not any("station A's frame changed" in d for d in agreement["differences"])
    assert agreement["check_by_station"]["B"]["frame_changed"] is True


def test_declared_sigma_sets_the_floor_over_a_probes_virtual_reflectors() -> None:
    """A probe turned into virtual reflectors: their mutual distances are exact, the floor inferred
    from them is no floor at all; the declared σ (column or option) is."""
    camp = make_campaign("kr210", 64, [], repeat_fraction=0.0)
    ds = camp.dataset
    assert ds.xyz_mm is not None
    n = len(ds)
    rot = rotvec_to_matrix(np.random.default_rng(0).normal(size=(n, 3)))
    virtual = ds.xyz_mm[:, None, :] + 100.0 * np.swapaxes(rot, 1, 2)[:, :2, :]  # exact: 100 mm along x, y
    probe = dataclasses.replace(ds, more_xyz_mm=virtual, sigma_mm=np.full(n, 0.02))
    obs = MeasuredRows.of_dataset(probe)
    floor, source = _noise_floor(obs, None, probe.reflectors_mm, probe.sigma_mm)
    assert source == "declared" and floor == pytest.approx(np.sqrt(3.0) * 0.02)
    floor, source = _noise_floor(obs, 0.05, probe.reflectors_mm, probe.sigma_mm)
    assert source == "declared" and floor == pytest.approx(np.sqrt(3.0) * 0.05)
    without = dataclasses.replace(probe, sigma_mm=None)
    floor, source = _noise_floor(MeasuredRows.of_dataset(without), None, without.reflectors_mm, None)
    assert source == "targets" and floor < 1e-6  # what the σ column overrides


def test_diagnosis_takes_the_probe_orientation_and_the_stations(two_stations: Path, tmp_path: Path) -> None:
    out = tmp_path / "diag.json"
    assert main(["diagnose", str(two_stations), "--robot", "kr210", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert "three further targets along its axes" in doc["frame"]["orientation"]
    angles = {k: v["angle_deg"] for k, v in doc["frame"]["stations"]["stations"].items()}
    assert sorted(angles.values()) == [0.0, pytest.approx(50.0, abs=0.05)]
    assert doc["noise_floor_source"] == "declared"
    assert doc["noise_floor_mm"] == pytest.approx(np.sqrt(3.0) * TRACKER_SIGMA_MM)
    assert doc["steps"][0]["check_rms_mm"] < 3.0 * doc["noise_floor_mm"]


def test_probe_axis_points_carry_a_rotation_with_the_stated_weight() -> None:
    q = matrix_to_quat(rotvec_to_matrix(np.array([[0.3, -0.5, 0.2]])))
    dtheta = np.array([2e-6, -1e-6, 3e-6])
    turned = matrix_to_quat(rotvec_to_matrix(dtheta[None]) @ quat_to_matrix(q))
    lever = orientation_weight(0.02, 0.01)
    a = probe_axis_points_mm(np.zeros((1, 3)), q, lever)
    b = probe_axis_points_mm(np.zeros((1, 3)), turned, lever)
    moved2 = float(np.sum((a - b) ** 2))
    assert moved2 == pytest.approx(2.0 * lever**2 * float(dtheta @ dtheta), rel=1e-4)
    # at the probe's σ per axis, the points move as far as the position's σ per axis
    assert lever * np.radians(0.01) * np.sqrt(2.0) == pytest.approx(0.02)


def test_export_judges_the_check_rows_of_two_stations_each_in_its_frame(
    two_stations: Path, tmp_path: Path
) -> None:
    model = tmp_path / "m.json"
    assert (
        main(["fit", str(two_stations), "--robot", "kr210", "--model", "kinematic", "--out", str(model)]) == 0
    )
    urdf = tmp_path / "cal.urdf"
    argv = [
        "export",
        "params",
        "--model",
        str(model),
        "--format",
        "urdf",
        "-o",
        str(urdf),
        "--data",
        str(two_stations),
    ]
    assert main(argv) == 0
    line = next(x for x in urdf.read_text().splitlines() if "check RMS" in x)
    assert float(line.split("check RMS:")[1].split("mm")[0]) < 3.0 * np.sqrt(3.0) * TRACKER_SIGMA_MM


def test_a_station_with_too_few_fit_rows_is_refused_by_name(two_stations: Path, tmp_path: Path) -> None:
    ds = read_dataset_file(two_stations)
    assert ds.station is not None and ds.split is not None
    b_fit = np.flatnonzero((np.asarray(ds.station) == "B") & (np.asarray(ds.split) == "fit"))
    split = np.asarray(ds.split).copy()
    split[b_fit[3:]] = "check"  # three fit rows left in station B
    few = tmp_path / "few.csv"
    write_dataset(dataclasses.replace(ds, split=split), few)
    with pytest.raises(CampaignError, match=r"station B \(3\) fit rows: fewer than the 6"):
        prepare_campaign(read_dataset_file(few), load_robot("kr210"))
