"""Approach directions inferred from the pose order agree with the motion that produced them."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.data.directions import infer_directions
from comp_daemon.data.table import Dataset
from comp_daemon.preparation.campaign import prepare_directions


def test_sign_of_last_motion_carried_over_still_axes() -> None:
    a = np.zeros((5, 6))
    a[:, 0] = [0.0, 10.0, 5.0, 5.0, 7.0]  # +, -, still (keeps -), +
    a[:, 1] = [0.0, 0.0, 0.0, -3.0, -3.0]  # unknown, unknown, unknown, -, still
    inf = infer_directions(a)
    assert inf.dir[:, 0].tolist() == [1, 1, -1, -1, 1]
    assert inf.assumed[:, 0].tolist() == [True, False, False, False, False]
    assert inf.dir[:, 1].tolist() == [1, 1, 1, -1, -1]
    assert inf.assumed[:, 1].tolist() == [True, True, True, False, False]
    assert inf.assumed_rows == 5  # axes 3..6 never move
    assert "row order" in inf.describe()
    assert "A1 1, A2 3, A3 5" in inf.describe()


def test_time_column_orders_the_rows() -> None:
    rng = np.random.default_rng(3)
    visited = np.cumsum(rng.normal(size=(40, 6)), axis=0)
    in_order = infer_directions(visited)
    perm = rng.permutation(40)
    shuffled = infer_directions(visited[perm], t_s=np.arange(40.0)[perm])
    np.testing.assert_array_equal(shuffled.dir, in_order.dir[perm])
    assert shuffled.order == "t_s"


def test_matches_the_direction_a_path_was_driven_with() -> None:
    rng = np.random.default_rng(7)
    a = np.cumsum(rng.uniform(-5, 5, size=(200, 6)), axis=0)
    truth = np.sign(np.diff(a, axis=0))
    inf = infer_directions(a)
    np.testing.assert_array_equal(inf.dir[1:], truth.astype(np.int8))


def test_dataset_with_dir_is_left_alone_and_bad_shapes_refused() -> None:
    a = np.zeros((3, 6))
    a[:, 2] = [0.0, 1.0, 0.5]
    ds = Dataset(a_deg=a, xyz_mm=np.zeros((3, 3)))
    filled, inf = prepare_directions(ds)
    assert inf.inferred and filled.dir is not None and filled.dir[:, 2].tolist() == [1, 1, -1]
    again, columns = prepare_directions(filled)
    assert columns.source == "columns" and again is filled
    untouched, none = prepare_directions(ds, need=False)
    assert none.source == "none" and untouched is ds
    with pytest.raises(ValueError, match=r"\(n, 6\)"):
        infer_directions(np.zeros((3, 5)))
