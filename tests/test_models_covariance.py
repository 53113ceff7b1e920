"""Prediction uncertainty: parameter covariance through the Jacobian, kriging variance, the doors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, read_dataset, write_dataset
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.artifact import load_model, save_model
from comp_daemon.models.covariance import covariance_from_fit
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.registry import fit_model, fit_spec, parse_model_name
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")
SCENARIOS = Path(__file__).resolve().parents[1] / "comp_daemon" / "sim" / "scenarios"
REPEATABILITY_DEG = np.array([0.0004, 0.0004, 0.0004, 0.0008, 0.0008, 0.0008])  # kr210-geometric
TRACKER_SIGMA_MM = 0.01  # kr210-geometric


def _axes(n: int, seed: int) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 90.0)


def test_covariance_of_a_linear_fit_is_the_textbook_one() -> None:
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(50, 3)) * [1.0, 100.0, 0.01]
    res = rng.normal(size=50)
    cov, s = covariance_from_fit(jac, res)
    s2 = res @ res / 47
    np.testing.assert_allclose(cov, s2 * np.linalg.inv(jac.T @ jac), rtol=1e-9)
    assert s == pytest.approx(np.sqrt(s2))


def test_kinematic_sigma_matches_the_spread_of_refits() -> None:
    """Monte Carlo: refit on redrawn noise; the spread of the predictions is the predicted σ."""
    rng = np.random.default_rng(3)
    a, a_new = _axes(70, 1), _axes(15, 2)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    p_true = tcp_position_mm(truth, axes_deg_to_q_rad(a, truth.sign))
    preds, sigmas = [], []
    for _ in range(25):
        fitted = fit_model("kinematic", KR, a, p_true + rng.normal(size=p_true.shape) * 0.02, frame="base")
        preds.append(fitted.model.predict_tcp_mm(a_new))
        sigma = fitted.model.predict_std_mm(a_new)
        assert sigma is not None
        sigmas.append(sigma)
    spread = np.std(np.array(preds), axis=0, ddof=1)
    ratio = np.mean(spread) / np.mean(np.array(sigmas))
    assert 0.75 < ratio < 1.33, ratio


def _noise_sd(a: np.ndarray) -> np.ndarray:
    """Per-coordinate measurement noise the scenario declares: tracker σ and joint repeatability."""
    nom = KinematicParams.from_robot(KR)
    p0 = tcp_position_mm(nom, axes_deg_to_q_rad(a, nom.sign))
    var = np.full(p0.shape, TRACKER_SIGMA_MM**2)
    for j in range(6):
        b = a.copy()
        b[:, j] += 1e-4
        var += (
            (tcp_position_mm(nom, axes_deg_to_q_rad(b, nom.sign)) - p0) / 1e-4 * REPEATABILITY_DEG[j]
        ) ** 2
    return np.sqrt(var)


@pytest.fixture(scope="module")
def geometric(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("geo") / "geo.csv"
    scenario = str(SCENARIOS / "kr210-geometric.toml")
    assert main(["sim", "sample", "--scenario", scenario, "--n", "300", "--out", str(path)]) == 0
    return path


@pytest.mark.parametrize("n_fit", [60, None])
def test_kinematic_sigma_is_calibrated_on_check_rows(geometric: Path, n_fit: int | None) -> None:
    ds = read_dataset(geometric)
    fit_rows = ds.fit_rows()[:n_fit]
    check = np.flatnonzero(ds.split == "check")
    model = fit_spec(parse_model_name("kinematic"), KR, MeasuredRows.of_dataset(ds).take(fit_rows)).model
    a = ds.a_deg[check]
    err = ds.xyz_mm[check] - model.predict_tcp_mm(a)
    sigma = model.predict_std_mm(a)
    assert sigma is not None and np.all(sigma > 0)
    total = np.sqrt(sigma**2 + _noise_sd(a) ** 2)
    inside = float(np.mean(np.abs(err) < 2.0 * total))
    assert 0.90 <= inside <= 0.99, inside


@pytest.mark.parametrize("name", ["kinematic+ratio+backlash", "chebyshev", "compliance"])
def test_sigma_survives_the_artifact_and_shrinks_with_rows(
    geometric: Path, tmp_path: Path, name: str
) -> None:
    ds = read_dataset(geometric)
    check = np.flatnonzero(ds.split == "check")[:20]
    a, d = ds.a_deg[check], ds.dir[check].astype(float)
    few = fit_spec(parse_model_name(name), KR, MeasuredRows.of_dataset(ds).take(ds.fit_rows()[:70])).model
    many = fit_spec(parse_model_name(name), KR, MeasuredRows.of_dataset(ds).take(ds.fit_rows())).model
    s_few, s_many = few.predict_std_mm(a, d), many.predict_std_mm(a, d)
    assert s_few is not None and s_many is not None
    assert np.mean(s_many) < np.mean(s_few)
    save_model(many, tmp_path / "m.json", data_sha256="x", frame="base")
    loaded = load_model(tmp_path / "m.json", KR).model
    np.testing.assert_array_equal(loaded.predict_std_mm(a, d), s_many)


def test_kriging_sigma_is_small_at_samples_and_grows_away() -> None:
    rng = np.random.default_rng(5)
    a = _axes(150, 7)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros(2).with_values(["c2_1", "s3_1"], [0.003, 0.002])
    p = twin_tcp_mm(KR, truth, eff, a) + rng.normal(size=(150, 3)) * 0.005
    model = fit_model("kriging", KR, a, p, frame="base").model
    at_samples = model.predict_std_mm(a[:10])
    far = model.predict_std_mm(_axes(10, 99))
    assert at_samples is not None and far is not None
    assert np.mean(at_samples) < np.mean(far)


def test_compensate_writes_a_sigma_column(geometric: Path, tmp_path: Path) -> None:
    model_path = tmp_path / "kin.json"
    assert (
        main(["fit", str(geometric), "--robot", "kr210", "--model", "kinematic", "--out", str(model_path)])
        == 0
    )
    ds = read_dataset(geometric)
    targets = tmp_path / "targets.csv"
    write_dataset(Dataset(a_deg=ds.a_deg[:8]), targets)
    out = tmp_path / "out.csv"
    assert main(["compensate", str(model_path), str(targets), "--out", str(out)]) == 0
    sigma = np.array([float(v) for v in read_dataset(out, kind="targets").extra["predicted_sigma_mm"]])
    model = load_model(model_path, KR).model
    corrected = read_dataset(out, kind="targets").a_deg
    expected = np.linalg.norm(model.predict_std_mm(corrected), axis=1)
    np.testing.assert_allclose(sigma, expected, rtol=1e-12)
    assert np.all((sigma > 0) & (sigma < 0.05))
