"""The rotations and numbers of the export listings: every conversion read back to the same frame."""

from __future__ import annotations

import numpy as np

from comp_daemon.export.frames import (
    matrix_to_quaternion,
    matrix_to_rotvec_deg,
    num,
    quaternion_to_matrix,
    rotvec_deg_to_matrix,
)
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix, matrix_to_abc_deg
from comp_daemon.kinematics.so3 import rotvec_to_matrix


def _rotations() -> np.ndarray:
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [rng.uniform(0, np.pi, 150), np.pi - 10.0 ** -rng.uniform(3, 12, 40), [np.pi] * 5, [0.0] * 5]
    )
    rots = rotvec_to_matrix(axes * angles[:, None])
    gimbal = abc_deg_to_matrix(np.array([[30.0, 90.0, 0.0], [-70.0, -90.0, 0.0], [10.0, 89.9999, 5.0]]))
    return np.concatenate([rots, gimbal])


def test_every_rotation_form_reads_back_to_the_same_matrix() -> None:
    rots = _rotations()
    for back in (
        abc_deg_to_matrix(matrix_to_abc_deg(rots)),
        quaternion_to_matrix(matrix_to_quaternion(rots)),
        rotvec_deg_to_matrix(matrix_to_rotvec_deg(rots)),
    ):
        assert np.abs(back - rots).max() < 1e-9


def test_abc_is_kukas_order_and_quaternions_are_w_first() -> None:
    abc = np.array([20.0, -35.0, 170.0])
    np.testing.assert_allclose(matrix_to_abc_deg(abc_deg_to_matrix(abc)), abc, atol=1e-12)
    q = matrix_to_quaternion(rotvec_to_matrix(np.array([0.0, 0.0, np.pi / 2])))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], atol=1e-15)


def test_numbers_read_back_exactly_without_exponent() -> None:
    rng = np.random.default_rng(4)
    values = np.concatenate(
        [rng.normal(size=200) * 10.0 ** rng.integers(-12, 5, 200), [0.0, -0.0, 1e-20, 90.0]]
    )
    for v in values:
        text = num(v)
        assert float(text) == v and "e" not in text.lower()
    assert num(-0.0) == "0.0" and num(25.0) == "25.0"
