"""The uncertainty mode of a ballbar campaign (spec A.8) through ``fit``: repeats give each pose's
standard and expanded uncertainty, the fit is weighted by them, the nested correction runs, and the
reported parameter uncertainty matches the spread of the parameters over noisy campaigns."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from comp_daemon.cli import main
from comp_daemon.data.ballbar import ballbar_dataset, read_ballbar
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.dataset import dataset_to_csv
from comp_daemon.estimation.uncertainty import covariance_scale
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, ballbar_lengths_mm
from comp_daemon.instruments.ballbar_plan import TABLE5_ERRORS, ballbar_plan
from comp_daemon.instruments.campaign_fit import fit_ballbar_campaign
from comp_daemon.kinematics.poe import irb120_table1
from comp_daemon.models.artifact import load_model
from comp_daemon.models.covariance import ParameterCovariance
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")
PLAN = ballbar_plan(ROBOT, 3)
TRUTH = np.concatenate([TABLE5_ERRORS, [0.8, -0.6, 0.5]])
EXACT = ballbar_lengths_mm(irb120_table1(ROBOT), PLAN.a_deg, TRUTH, PAPER_PIVOT_MM)
SIGMA_MM = 0.0035  # spec A.9's reading noise
REPEATS = 5


def _campaign_csv(seed: int, sigma: float | NDArray[np.float64] = SIGMA_MM, repeats: int = REPEATS) -> str:
    """The 3-arc plan measured ``repeats`` times (one pass after the other), noise σ per pose."""
    rng = np.random.default_rng(seed)
    n = EXACT.size
    noise = rng.normal(0.0, 1.0, (repeats, n)) * np.broadcast_to(sigma, (n,))
    ds = ballbar_dataset(
        np.tile(PLAN.a_deg, (repeats, 1)),
        np.tile(PLAN.arc, repeats),
        PAPER_PIVOT_MM,
        bar_mm=(EXACT[None, :] + noise).ravel(),
        pose_id=tuple(f"p{i}" for i in np.tile(np.arange(n), repeats)),
        repeat=np.repeat(np.arange(repeats), n),
    )
    return dataset_to_csv(ds)


def test_repeats_turn_the_uncertainty_mode_on_and_a_pose_without_repeats_is_refused() -> None:
    text = _campaign_csv(0)
    campaign = read_ballbar(text)
    assert campaign.repeated
    groups = campaign.repeat_groups()
    assert len(groups) == EXACT.size and all(g.size == REPEATS for g in groups)
    lines = text.splitlines()
    with pytest.raises(DatasetError, match="at least 2") as err:
        read_ballbar("\n".join(lines[: 1 + EXACT.size + 1]) + "\n")  # one pose repeated, the rest once
    assert err.value.column == "pose_id" and err.value.row is not None
    mixed = read_ballbar("\n".join(lines[: 1 + EXACT.size + 1]) + "\n", uncertainty=False)
    with pytest.raises(ValueError, match="at least 2 repeats of every pose"):
        fit_ballbar_campaign(ROBOT, mixed)


def test_u_b_weights_and_the_nested_loop_are_reported_with_the_fit() -> None:
    sigma = np.where(PLAN.arc == 2, 3 * SIGMA_MM, SIGMA_MM)  # arc 2 three times noisier
    fitted = fit_ballbar_campaign(ROBOT, read_ballbar(_campaign_csv(1, sigma)))
    unc = fitted.info["uncertainty"]
    u = np.array(unc["per_pose"]["u_mm"])
    assert u.size == EXACT.size
    assert np.allclose(unc["per_pose"]["b_mm"], 1.96 * u)
    # the repeats see the noise: arc 2's u is about 3 times the others'
    assert 2.0 < np.median(u[PLAN.arc == 2]) / np.median(u[PLAN.arc != 2]) < 4.5
    assert 0.5 < unc["weighted"]["chi2_per_dof"] < 2.0  # the model explains the readings to their u
    nested = unc["nested"]
    assert nested["stop"] in ("converged", "unchanged", "max_rounds") and nested["rounds"]
    assert nested["rounds"][0]["corrected"] > 0
    if nested["stop"] == "converged":
        # converged: every residual within b/4, except those beyond b, flagged (model error or a
        # reading whose u the repeats underestimated): a few of 103 at most
        assert nested["flagged"] <= 0.05 * u.size
        assert nested["flagged"] > 0 or nested["max_abs_residual_over_b"] <= 0.25 + 1e-9
    # weighted and unweighted fits side by side; the model carries the identified POE errors' covariance
    assert set(unc["weighted"]["identified"]) == set(unc["unweighted"]["identified"])
    cov = fitted.model.uncertainty
    assert isinstance(cov, ParameterCovariance)
    poe = [n for n in fitted.info["identified"] if n.startswith(("dl", "dtheta"))]
    assert list(cov.names) == poe
    assert fitted.info["solver"]["method"].endswith("nested correction")
    # before: the nominal model's length error (Table 5 errors, tenths of a mm); after: the noise
    assert fitted.info["bar_rms_before_mm"] > 0.05 and fitted.info["bar_rms_after_mm"] < 0.02


def test_reported_uncertainty_matches_the_spread_over_noisy_campaigns() -> None:
    """20 noisy campaigns of the same robot: each well-determined parameter's spread lies within a
    factor 1.5 of the σ the fit reports, and so does the spread of the predicted TCP."""
    names = ("dl4", "dtheta2", "dtheta3", "dtheta4", "dYo", "dZo")
    probe = PLAN.a_deg[::20]
    values, stds, tcps, tcp_std = [], [], [], []
    for seed in range(20):
        fitted = fit_ballbar_campaign(ROBOT, read_ballbar(_campaign_csv(100 + seed)))
        ident = fitted.info["identified"]
        values.append([ident[n]["value"] for n in names])
        stds.append([ident[n]["std"] for n in names])
        tcps.append(fitted.model.predict_tcp_mm(probe))
        std = fitted.model.predict_std_mm(probe)
        assert std is not None
        tcp_std.append(std)
    spread = np.std(values, axis=0, ddof=1)
    reported = np.mean(stds, axis=0)
    ratio = spread / reported
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), dict(zip(names, ratio.round(2), strict=True))
    tcp_spread = np.std(tcps, axis=0, ddof=1)  # (points, 3)
    tcp_reported = np.mean(tcp_std, axis=0)
    big = tcp_reported > 1e-3  # coordinates the identified parameters move
    tcp_ratio = np.median(tcp_spread[big] / tcp_reported[big])
    assert 1 / 1.5 < tcp_ratio < 1.5, tcp_ratio


def test_fit_cli_prints_and_saves_the_uncertainty_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "ballbar.csv"
    data.write_text(_campaign_csv(2))
    out = tmp_path / "model.json"
    assert main(["fit", str(data), "--robot", "irb120", "--model", "poe", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "uncertainty (spec A.8)" in text and f"x {REPEATS} repeats" in text
    assert "nested correction" in text and "U(95 %)" in text
    doc = json.loads(out.read_text())
    unc = doc["fit"]["uncertainty"]
    assert unc["poses"] == EXACT.size and unc["repeats"] == {"min": REPEATS, "max": REPEATS}
    assert 2.0e-3 < unc["u_mm"]["mean"] < 5.0e-3  # σ = 3.5 µm
    loaded = load_model(str(out), ROBOT)
    std = loaded.model.predict_std_mm(PLAN.a_deg[:5])
    assert std is not None and np.all(np.isfinite(std)) and std.max() < 0.1


def test_covariance_scale_widens_only_for_a_model_that_misses_the_readings_uncertainty() -> None:
    w = np.full(6, 4.0)  # u = 0.5 on every reading
    # residuals of twice u: chi2 = 6 * 4 * 1 = 24 over 6 - 2 = 4 degrees of freedom
    assert covariance_scale(w, np.full(6, 1.0), 2) == (6.0, 6.0)
    # residuals well inside u: the reduced chi2 is reported, the covariance keeps its size
    chi2_nu, scale = covariance_scale(w, np.full(6, 0.1), 2)
    assert chi2_nu == pytest.approx(0.06) and scale == 1.0
    # no degree of freedom left: nu counts as 1, not 0 or negative
    assert covariance_scale(w, np.full(6, 1.0), 6) == (24.0, 24.0)


def test_the_models_sigma_per_length_is_the_repeats_or_the_residual_with_its_degrees_of_freedom() -> None:
    repeated = fit_ballbar_campaign(ROBOT, read_ballbar(_campaign_csv(3)))
    u = np.array(repeated.info["uncertainty"]["per_pose"]["u_mm"])
    cov = repeated.model.uncertainty
    assert isinstance(cov, ParameterCovariance)
    assert cov.sigma_mm == pytest.approx(np.sqrt(np.mean(np.maximum(u, 0.5e-3) ** 2)), rel=1e-12)
    assert cov.rows == EXACT.size
    single = fit_ballbar_campaign(ROBOT, read_ballbar(_campaign_csv(3, repeats=1)))
    n, p = EXACT.size, len(single.info["identified"])
    cov = single.model.uncertainty
    assert isinstance(cov, ParameterCovariance) and "uncertainty" not in single.info
    assert cov.sigma_mm == pytest.approx(single.info["rms_mm"] * np.sqrt(n / (n - p)), rel=1e-12)
    assert cov.rows == n
