"""The data set's per-row sigma_mm weights the kinematic fit (weighted least squares)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, write_dataset
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.artifact import load_model
from comp_daemon.models.kinematic import KinematicModel, calibrate_kinematic
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")


def _campaign(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, KinematicModel]:
    """120 poses of a KR 210 with geometric errors; half measured with σ 0.003 mm, half with 0.3 mm."""
    rng = np.random.default_rng(seed)
    mid = KR.axis_limits_deg.mean(axis=1)
    a = mid + rng.uniform(-40, 40, (120, 6))
    truth = KinematicModel(KR, KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4))
    sigma = np.where(np.arange(120) % 2 == 0, 0.003, 0.3)
    p = truth.predict_tcp_mm(a) + rng.normal(size=(120, 3)) * sigma[:, None]
    return a, p, sigma, truth


def _truth_error(model: KinematicModel, truth: KinematicModel) -> float:
    a = KR.axis_limits_deg.mean(axis=1) + np.random.default_rng(99).uniform(-40, 40, (200, 6))
    return float(np.sqrt(np.mean(np.sum((model.predict_tcp_mm(a) - truth.predict_tcp_mm(a)) ** 2, axis=1))))


def test_weights_follow_the_declared_sigma() -> None:
    a, p, sigma, truth = _campaign(0)
    plain = calibrate_kinematic(KR, a, p, frame="base")
    weighted = calibrate_kinematic(KR, a, p, frame="base", sigma_mm=sigma)
    assert weighted.weighted and not plain.weighted
    plain_err, weighted_err = _truth_error(plain.model, truth), _truth_error(weighted.model, truth)
    assert weighted_err < 0.3 * plain_err, (weighted_err, plain_err)
    # the RMS it reports is of the measured positions, unweighted
    residual = weighted.model.predict_tcp_mm(a) - p
    assert weighted.rms_mm == pytest.approx(float(np.sqrt(np.mean(np.sum(residual**2, axis=1)))), rel=1e-9)
    with pytest.raises(ValueError, match="sigma_mm must be"):
        calibrate_kinematic(KR, a, p, frame="base", sigma_mm=np.zeros(120))


def test_fit_takes_the_sigma_column(tmp_path: Path) -> None:
    a, p, sigma, truth = _campaign(1)
    with_sigma, without = tmp_path / "sigma.csv", tmp_path / "plain.csv"
    write_dataset(Dataset(a_deg=a, xyz_mm=p, sigma_mm=sigma), with_sigma)
    write_dataset(Dataset(a_deg=a, xyz_mm=p), without)
    errors = {}
    for path in (with_sigma, without):
        out = tmp_path / f"{path.stem}.json"
        assert (
            main(
                [
                    "fit",
                    str(path),
                    "--robot",
                    "kr210",
                    "--model",
                    "kinematic",
                    "--frame",
                    "base",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        loaded = load_model(out, KR)
        assert isinstance(loaded.model, KinematicModel)
        errors[path.stem] = _truth_error(loaded.model, truth)
        weighting = loaded.document["fit"].get("weighting")
        assert (weighting is not None) == (path is with_sigma)
    assert errors["sigma"] < 0.3 * errors["plain"], errors
