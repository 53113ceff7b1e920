"""The one type of measured rows: built from a data set once, cut and stacked with every column."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comp_daemon.data.table import Dataset
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.effects import EffectParams, MassModel, effect_data, twin_inputs_of, twin_state
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG, MeasuredRows
from comp_daemon.robot.description import load_robot

N = 8
PER_ROW = [f.name for f in dataclasses.fields(MeasuredRows) if f.metadata.get("per_row")]


def _campaign(**change: object) -> Dataset:
    """Eight rows, four poses measured twice, every optional column; ``change`` replaces some."""
    rng = np.random.default_rng(3)
    poses = rng.uniform(-40.0, 40.0, (4, 6))
    a = np.concatenate([poses, poses])  # rows i and i + 4: one pose
    q = Rotation.random(N, random_state=5).as_quat(scalar_first=True)
    columns: dict[str, object] = {
        "a_deg": a,
        "xyz_mm": rng.normal(size=(N, 3)) * 100.0 + 1000.0,
        "dir": np.where(rng.random((N, 6)) < 0.5, -1, 1),
        "payload_kg": np.array([0.0, 5.0] * 4),
        "temp_c": np.linspace(20.0, 23.5, N),
        "t_s": 7200.0 + 900.0 * np.arange(N),
        "pose_id": ("p3", "p1", "p2", "p0") * 2,
        "more_xyz_mm": rng.normal(size=(N, 2, 3)) + 1000.0,
        "station": ("B", "A", "B", "C", "A", "A", "C", "B"),
        "probe_q_wxyz": q,
        "sigma_mm": np.linspace(0.01, 0.03, N),
    }
    columns.update(change)
    return Dataset(**columns)  # type: ignore[arg-type]


def test_the_rows_of_a_campaign_carry_every_column() -> None:
    ds = _campaign()
    unknown = np.zeros((N, 6), dtype=bool)
    unknown[0, 2] = unknown[5, 0] = True
    rows = MeasuredRows.of_dataset(ds, unknown, probe_sigma_deg=0.02)
    assert rows.n == len(rows) == N
    np.testing.assert_array_equal(rows.a_deg, ds.a_deg)
    np.testing.assert_array_equal(rows.xyz_mm, ds.xyz_mm)
    assert ds.dir is not None
    want_dir = ds.dir.astype(float)
    want_dir[0, 2] = want_dir[5, 0] = 0.0  # unknown directions are 0
    np.testing.assert_array_equal(rows.dir, want_dir)
    np.testing.assert_array_equal(rows.payload_kg, ds.payload_kg)
    np.testing.assert_array_equal(rows.temp_c, ds.temp_c)
    np.testing.assert_array_equal(rows.more_xyz_mm, ds.more_xyz_mm)
    np.testing.assert_array_equal(rows.sigma_mm, ds.sigma_mm)
    # stations numbered in the sorted order of their names
    assert rows.station_names == ("A", "B", "C")
    np.testing.assert_array_equal(rows.station, [1, 0, 1, 2, 0, 0, 2, 1])
    # the probe's quaternions (w first) as rotations
    assert ds.probe_q_wxyz is not None and rows.probe_r is not None
    np.testing.assert_allclose(rows.probe_r @ np.array([1.0, 0.0, 0.0]), _x_axis(ds.probe_q_wxyz), atol=1e-12)
    assert rows.probe_sigma_deg == 0.02
    # pose groups by pose_id: the repeats share one
    np.testing.assert_array_equal(rows.pose_group[:4], rows.pose_group[4:])
    assert len(np.unique(rows.pose_group)) == 4
    # the clock: hours since the first t_s
    np.testing.assert_allclose(rows.clock, 0.25 * np.arange(N))
    assert rows.clock_name == "t_s"
    assert rows.target is None and rows.target_offsets_mm is None


def _x_axis(q_wxyz: np.ndarray) -> np.ndarray:
    """The x axis of the rotation of unit quaternions (w first), written out."""
    w, x, y, z = q_wxyz.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=1)


def test_a_campaign_without_directions_times_or_ids_takes_the_defaults() -> None:
    a = _campaign().a_deg
    assert a is not None
    ds = _campaign(
        dir=None, t_s=None, pose_id=None, station=None, probe_q_wxyz=None, sigma_mm=None, more_xyz_mm=None
    )
    rows = MeasuredRows.of_dataset(ds)
    assert rows.dir is None and rows.station is None and rows.station_names is None
    assert rows.probe_r is None and rows.sigma_mm is None and rows.more_xyz_mm is None
    assert rows.probe_sigma_deg == DEFAULT_PROBE_SIGMA_DEG
    # no times: the clock is the row order; no pose ids: identical axis values are one pose
    np.testing.assert_array_equal(rows.clock, np.arange(N, dtype=float))
    assert rows.clock_name == "pose_order"
    np.testing.assert_array_equal(rows.pose_group[:4], rows.pose_group[4:])
    assert len(np.unique(rows.pose_group)) == 4
    # the same groups when the rows are given without a data set
    given = MeasuredRows(ds.a_deg, ds.xyz_mm)  # type: ignore[arg-type]
    np.testing.assert_array_equal(given.pose_group, rows.pose_group)
    np.testing.assert_array_equal(given.payload_kg, np.zeros(N))
    assert given.clock is None


def test_a_campaign_without_positions_is_refused_by_name() -> None:
    ds = _campaign(xyz_mm=None, more_xyz_mm=None, probe_q_wxyz=None)
    with pytest.raises(
        ValueError, match=r"<memory>: measured rows need axis values a1\.\.a6 and measured x, y, z"
    ):
        MeasuredRows.of_dataset(ds)


def test_a_column_of_another_length_is_refused_by_name() -> None:
    rows = MeasuredRows.of_dataset(_campaign())
    with pytest.raises(ValueError, match=r"temp_c: expected 8 rows like the axis values, got 3"):
        dataclasses.replace(rows, temp_c=np.zeros(3))
    with pytest.raises(ValueError, match=r"payload_kg: expected a number or shape \(8,\)"):
        MeasuredRows(rows.a_deg, rows.xyz_mm, payload_kg=np.zeros(5))


def test_take_keeps_every_column() -> None:
    rows = MeasuredRows.of_dataset(_campaign(), probe_sigma_deg=0.03)
    pick = np.array([6, 1, 1, 3])
    sub = rows.take(pick)
    assert sub.n == 4
    for name in PER_ROW:
        whole = getattr(rows, name)
        if whole is not None:
            np.testing.assert_array_equal(getattr(sub, name), whole[pick], err_msg=name)
    assert (sub.station_names, sub.probe_sigma_deg, sub.clock_name) == (rows.station_names, 0.03, "t_s")


def test_stacked_targets_are_rows_of_their_own_with_every_column() -> None:
    rows = MeasuredRows.of_dataset(_campaign())
    assert rows.more_xyz_mm is not None
    offsets = np.array([[10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    every = rows.stack_targets(rows.more_xyz_mm, offsets)
    assert every.n == 3 * N and every.more_xyz_mm is None
    np.testing.assert_array_equal(every.target, np.repeat([0, 1, 2], N))
    np.testing.assert_array_equal(every.target_offsets_mm, offsets)
    for k in range(3):  # row i + k·n is target k of pose i
        block = slice(k * N, (k + 1) * N)
        want = rows.xyz_mm if k == 0 else rows.more_xyz_mm[:, k - 1]
        np.testing.assert_array_equal(every.xyz_mm[block], want)
        for name in PER_ROW:
            if name not in ("xyz_mm", "more_xyz_mm", "target"):
                np.testing.assert_array_equal(getattr(every, name)[block], getattr(rows, name), err_msg=name)
    # per target again: the rows of each, the target's place on the flange
    parts = every.by_target()
    assert [None if off is None else off.tolist() for _, _, off in parts] == [None, *offsets.tolist()]
    for k, (idx, sub, _) in enumerate(parts):
        np.testing.assert_array_equal(idx, np.arange(k * N, (k + 1) * N))
        assert sub.target is None and sub.same_poses(rows)
    # taking rows of stacked targets keeps which target each is
    np.testing.assert_array_equal(every.take(np.array([0, N, 2 * N])).target, [0, 1, 2])


def test_what_the_effects_derive_comes_from_the_rows() -> None:
    robot = load_robot("kr210")
    mass, params = MassModel.from_robot(robot), KinematicParams.from_robot(robot)
    rows = MeasuredRows.of_dataset(_campaign())
    inputs = twin_inputs_of(mass, params, rows, t_ref_c=21.0, step_at=1.0)
    np.testing.assert_array_equal(inputs.a_deg, rows.a_deg)
    np.testing.assert_array_equal(inputs.clock, rows.clock)
    np.testing.assert_array_equal(inputs.delta_t_k, np.asarray(rows.temp_c) - 21.0)
    assert inputs.step_at == 1.0
    st = twin_state(
        mass,
        params,
        EffectParams.zeros(),
        rows.a_deg,
        rows.dir,
        rows.payload_kg,
        rows.temp_c,
        with_torques=True,
    )
    data = effect_data(mass, params, rows, np.ones(6, dtype=bool))
    np.testing.assert_array_equal(data.tau_nm, st.tau_nm)
    assert data.dir is rows.dir and data.temp_c is rows.temp_c and data.clock is rows.clock
