"""SO(3) helpers: round trips (near 0 and π too), batch shapes, the left Jacobian vs central differences."""

from __future__ import annotations

import numpy as np

from comp_daemon.kinematics.so3 import left_jacobian, matrix_to_rotvec, rotvec_to_matrix, skew


def _rotvecs(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.concatenate([rng.uniform(0, np.pi - 1e-3, n - 3), [0.0, 1e-9, np.pi - 1e-8]])
    return axis * angle[:, None]


def test_rotvec_round_trip_in_batch_and_single() -> None:
    r = _rotvecs(200, 1)
    mats = rotvec_to_matrix(r)
    assert mats.shape == (200, 3, 3)
    np.testing.assert_allclose(
        mats @ np.swapaxes(mats, -1, -2), np.broadcast_to(np.eye(3), mats.shape), atol=1e-12
    )
    np.testing.assert_allclose(matrix_to_rotvec(mats), r, atol=2e-7)
    np.testing.assert_allclose(rotvec_to_matrix(r[5]), mats[5], atol=0)
    np.testing.assert_allclose(matrix_to_rotvec(mats[5]), r[5], atol=1e-12)


def test_half_turn_is_recovered() -> None:
    r = np.array([0.0, 0.6, 0.8]) * np.pi
    np.testing.assert_allclose(
        rotvec_to_matrix(matrix_to_rotvec(rotvec_to_matrix(r))), rotvec_to_matrix(r), atol=1e-12
    )


def test_left_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(0)
    for r in (rng.normal(size=3) * 0.7, np.array([1e-8, -2e-8, 3e-9]), rng.normal(size=3) * 2.0):
        v = rng.normal(size=3)
        analytic = -skew(rotvec_to_matrix(r) @ v) @ left_jacobian(r)
        h = 1e-6
        num = np.stack(
            [
                (rotvec_to_matrix(r + h * e) @ v - rotvec_to_matrix(r - h * e) @ v) / (2 * h)
                for e in np.eye(3)
            ],
            axis=1,
        )
        np.testing.assert_allclose(analytic, num, atol=1e-8)
    batch = rng.normal(size=(4, 3))
    np.testing.assert_allclose(left_jacobian(batch)[2], left_jacobian(batch[2]), atol=0)
