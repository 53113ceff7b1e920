"""Scenarios, sampling campaigns, the `sim` command and the default scenario's figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import read_dataset
from comp_daemon.kinematics.forward import chain
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import FLANGE_R_KUKA_TOOL
from comp_daemon.sim.campaign import (
    iso9283_multidirection,
    raw_error_stats,
    run_campaign,
    sample_poses,
    visit_order,
)
from comp_daemon.sim.scenario import PRESET_SCENARIOS, ScenarioError, load_scenario, parse_scenario_toml
from comp_daemon.sim.tracker import LaserTracker

KR210_CELL = load_scenario("kr210-cell")


@pytest.mark.parametrize("name", PRESET_SCENARIOS)
def test_presets_load_and_their_hidden_robot_is_fixed(name: str) -> None:
    sc = load_scenario(name)
    assert sc.name == name
    np.testing.assert_array_equal(sc.true_dx(), load_scenario(name).true_dx())
    assert np.abs(sc.true_dx()).max() > 0.0


def test_geometric_scenario_is_the_cell_robot_without_effects() -> None:
    geo = load_scenario("kr210-geometric")
    np.testing.assert_array_equal(geo.true_dx(), KR210_CELL.true_dx())
    assert np.all(geo.effects.get(geo.effects.names()) == 0.0)
    assert np.any(KR210_CELL.effects.backlash_deg > 0)


def test_sampled_poses_are_a_latin_hypercube_reached_by_nominal_ik() -> None:
    n = 40
    poses = sample_poses(KR210_CELL, n, np.random.default_rng(5))
    cam = KR210_CELL.campaign
    assert np.all(poses.target_xyz_mm >= cam.box_min_mm) and np.all(poses.target_xyz_mm <= cam.box_max_mm)
    assert np.all(np.abs(poses.target_abc_deg) <= 10.0)
    assert poses.redrawn == 0  # the whole box is reachable: the design stays a Latin hypercube
    unit = (poses.target_xyz_mm - cam.box_min_mm) / (cam.box_max_mm - cam.box_min_mm)
    for col in unit.T:  # one sample in each of the n slices of every dimension
        assert sorted(np.floor(col * n).astype(int)) == list(range(n))
    params = KinematicParams.from_robot(KR210_CELL.robot)
    ch = chain(params, axes_deg_to_q_rad(poses.a_deg, params.sign))
    np.testing.assert_allclose(ch.tcp_mm, poses.target_xyz_mm, atol=1e-3)
    want_r = abc_deg_to_matrix(poses.target_abc_deg)
    np.testing.assert_allclose(ch.world_T_frame[:, 6, :3, :3] @ FLANGE_R_KUKA_TOOL, want_r, atol=1e-6)


def test_campaign_columns_come_from_the_motion() -> None:
    ds = run_campaign(KR210_CELL, 30, seed=4, repeats=2)
    assert ds.a_deg is not None and ds.dir is not None and ds.split is not None and ds.repeat is not None
    assert len(ds.a_deg) == 60
    # the route is one continuous motion: each row's dir is the sign of its move from the row before
    prev = np.vstack([KR210_CELL.campaign.home_deg, ds.a_deg[:-1]])
    step = ds.a_deg - prev
    moved = np.abs(step) > 1e-9
    np.testing.assert_array_equal(ds.dir[moved], np.sign(step[moved]).astype(np.int8))
    assert set(ds.payload_kg) == {0.0, 120.0}
    assert np.all(np.diff(ds.t_s) > 0)
    assert ds.temp_c is not None and ds.temp_c[-1] > ds.temp_c[0]
    # repeats measure the same poses, and a pose keeps its split
    assert ds.pose_id is not None
    first, second = ds.repeat == 0, ds.repeat == 1
    assert sorted(np.array(ds.pose_id)[first]) == sorted(np.array(ds.pose_id)[second])
    by_pose = {}
    for pid, split in zip(ds.pose_id, ds.split, strict=True):
        assert by_pose.setdefault(pid, split) == split
    assert (ds.split == "check").sum() == 2 * 12  # 40 % of 30 poses, twice
    # gratings read the output angle of joints 1-3 (within backlash and deflection of the command)
    assert ds.g_deg is not None
    np.testing.assert_array_equal(ds.g_present, [True, True, True, False, False, False])
    assert np.abs(ds.g_deg[:, :3] - ds.a_deg[:, :3]).max() < 0.05


def test_tracker_frame_is_a_rigid_transform_of_the_base_frame() -> None:
    base = run_campaign(KR210_CELL, 12, seed=2)
    tracked = run_campaign(KR210_CELL, 12, seed=2, in_tracker_frame=True)
    assert base.xyz_mm is not None and tracked.xyz_mm is not None
    t = KR210_CELL.tracker_T_base()
    expect = base.xyz_mm @ t[:3, :3].T + t[:3, 3]
    assert np.abs(tracked.xyz_mm - expect).max() < 0.1  # only the noise differs
    assert np.abs(tracked.xyz_mm - base.xyz_mm).max() > 100.0


def test_tracker_noise_has_its_sigma() -> None:
    tracker = LaserTracker(0.01, seed=1)
    pts = np.zeros((20000, 3))
    assert tracker.measure(pts).std(axis=0) == pytest.approx(np.full(3, 0.01), rel=0.05)
    with pytest.raises(ValueError, match="rigid"):
        LaserTracker(tracker_T_base=np.diag([2.0, 1.0, 1.0, 1.0]))


def test_default_scenario_raw_errors_look_like_seed_000_before() -> None:
    stats = raw_error_stats(KR210_CELL, run_campaign(KR210_CELL, 104, seed=11))
    assert 0.55 < stats.max_mm < 0.95
    assert 0.32 < stats.mean_mm < 0.52


def test_backlash_makes_multidirection_accuracy_exceed_three_repeatabilities() -> None:
    res = iso9283_multidirection(KR210_CELL, n_cycles=10)
    assert np.all(res.vap_mm > 3 * KR210_CELL.robot.repeatability_mm)
    assert np.all(res.ratio > 2.5)
    geo = iso9283_multidirection(load_scenario("kr210-geometric"), n_cycles=10)
    assert np.all(geo.ratio < 1.0)  # without backlash the directions agree within repeatability


def test_sim_sample_writes_a_dataset_the_reader_accepts(tmp_path: Path, capsys) -> None:
    out = tmp_path / "campaign.csv"
    assert (
        main(["sim", "sample", "--scenario", "kr210-cell", "--n", "25", "--out", str(out), "--seed", "3"])
        == 0
    )
    ds = read_dataset(out, limits_deg=KR210_CELL.robot.axis_limits_deg, min_rows=25)
    assert ds.a_deg is not None and len(ds.a_deg) == 25
    assert ds.dir is not None and ds.split is not None and ds.xyz_mm is not None
    assert "wrote 25 rows" in capsys.readouterr().err
    again = tmp_path / "again.csv"
    main(["sim", "sample", "--n", "25", "--out", str(again), "--seed", "3"])
    assert again.read_bytes() == out.read_bytes()  # reproducible


def test_sim_sample_refuses_bad_arguments(tmp_path: Path, capsys) -> None:
    assert main(["sim", "sample", "--n", "0", "--out", str(tmp_path / "x.csv")]) == 2
    assert "--n must be >= 1" in capsys.readouterr().err
    assert main(["sim", "sample", "--scenario", "nowhere", "--n", "3", "--out", str(tmp_path / "x.csv")]) == 2
    assert "scenario 'nowhere'" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda t: t.replace("[noise]", "[noise]\nbogus = 1"), r"\[noise\]: unknown field 'bogus'"),
        (
            lambda t: t.replace("backlash_deg = [0.006,", "backlash_deg = [0.006, 0.1,"),
            r"\[effects\]\.backlash_deg: expected shape \(6,\)",
        ),
        (
            lambda t: t.replace("box_max_mm = [2100.0", "box_max_mm = [1000.0"),
            "box_max_mm must exceed box_min_mm",
        ),
        (
            lambda t: t.replace("home_deg = [0.0, -85.0", "home_deg = [0.0, 10.0"),
            "home_deg: outside the axis limits",
        ),
        (lambda t: t + "\n[extra]\n", r"unknown table \[extra\]"),
    ],
)
def test_bad_scenarios_are_refused_by_field(edit, match: str) -> None:
    text = (Path(__file__).parents[1] / "comp_daemon/sim/scenarios/kr210-cell.toml").read_text()
    with pytest.raises(ScenarioError, match=match):
        parse_scenario_toml(edit(text), "test.toml")


def test_visit_order_changes_the_payload_once_each_and_starts_near_home() -> None:
    rng = np.random.default_rng(5)
    poses = sample_poses(KR210_CELL, 24, rng)
    loads = np.asarray(KR210_CELL.campaign.payload_kg)
    payload_of_pose = rng.permutation(np.resize(loads, 24))
    order = visit_order(KR210_CELL, poses.a_deg, payload_of_pose)
    assert sorted(order.tolist()) == list(range(24))  # every pose once
    visited = payload_of_pose[order]
    assert np.count_nonzero(np.diff(visited)) == len(loads) - 1  # one load change a payload
    assert visited[0] == loads[0]  # in the scenario's order of payloads
    first = np.flatnonzero(payload_of_pose == loads[0])
    time_from_home = np.max(
        np.abs(poses.a_deg[first] - KR210_CELL.campaign.home_deg) / KR210_CELL.motion.v_max_deg_s, axis=1
    )
    assert order[0] == first[np.argmin(time_from_home)]  # the nearest of its group to home first
