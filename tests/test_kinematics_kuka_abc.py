"""KUKA A, B, C and the flange rotation: checked against SciPy's Euler angles and the tool frame's axes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comp_daemon.kinematics.kuka_abc import (
    abc_deg_to_matrix,
    flange_rotation_of_tool_abc,
    matrix_to_abc_deg,
    tool_abc_of_flange_rotation,
)


def _abc(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-180, 180, n), rng.uniform(-89, 89, n), rng.uniform(-180, 180, n)])


def test_abc_is_intrinsic_zyx_as_scipy_defines_it() -> None:
    abc = _abc(50, 1)
    want = Rotation.from_euler("ZYX", abc, degrees=True).as_matrix()  # A about z, B about y', C about x''
    np.testing.assert_allclose(abc_deg_to_matrix(abc), want, atol=1e-12)
    np.testing.assert_allclose(matrix_to_abc_deg(want), abc, atol=1e-9)


def test_single_frame_and_batch_shapes() -> None:
    one = abc_deg_to_matrix([90.0, 0.0, 0.0])
    assert one.shape == (3, 3)
    np.testing.assert_allclose(one @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # A turns x towards y
    np.testing.assert_allclose(abc_deg_to_matrix([0.0, 0.0, 90.0]) @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    assert abc_deg_to_matrix(_abc(6, 2).reshape(2, 3, 3)).shape == (2, 3, 3, 3)


def test_tool_abc_orients_the_kuka_tool_frame_whose_x_is_the_flange_z() -> None:
    abc = _abc(20, 3)
    flange = flange_rotation_of_tool_abc(abc)
    tool = Rotation.from_euler("ZYX", abc, degrees=True).as_matrix()
    np.testing.assert_allclose(tool[:, :, 0], flange[:, :, 2], atol=1e-12)  # x_tool = z_flange
    np.testing.assert_allclose(tool[:, :, 1], flange[:, :, 1], atol=1e-12)  # y_tool = y_flange
    np.testing.assert_allclose(tool[:, :, 2], -flange[:, :, 0], atol=1e-12)  # z_tool = −x_flange
    np.testing.assert_allclose(tool_abc_of_flange_rotation(flange), abc, atol=1e-9)


def test_wrong_shapes_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="3 angles"):
        abc_deg_to_matrix([1.0, 2.0])
    with pytest.raises(ValueError, match=r"\(…, 3, 3\)"):
        matrix_to_abc_deg(np.eye(4))
