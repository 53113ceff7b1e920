"""The trial's numerics without the cell: plan, ISO 9283 statistics, histograms, verdict, JSON, report."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.sim.scenario import load_scenario
from comp_daemon.trial.plan import FULL, QUICK, TrialPlan, TrialSizes, plan_trial, visit_dirs
from comp_daemon.trial.report import render_html, render_text
from comp_daemon.trial.result import PointRun, TrialResult
from comp_daemon.trial.runner import trial_phases
from comp_daemon.trial.stats import histogram, iso9283_statistics
from comp_daemon.trial.verdict import verdict


def test_iso9283_statistics_on_known_positions() -> None:
    rng = np.random.default_rng(1)
    bary = np.array([[[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.4, 0.0]]])  # (1 point, 3 directions, 3)
    r = 0.02
    u = rng.normal(size=(1, 3, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    positions = np.stack([bary + r * u, bary - r * u], axis=2)  # ±r around each barycentre: l = r
    st = iso9283_statistics(positions)
    assert st["vap_mm"] == pytest.approx([0.5])  # |(0.3, 0, 0) − (0, 0.4, 0)|
    assert np.allclose(st["rp_mm"], r)  # l̄ = r, S_l = 0
    assert st["ratio"] == pytest.approx([0.5 / r])
    assert np.allclose(st["barycentres_mm"], bary)
    # against a direct loop over the definition on random data
    x = rng.normal(size=(2, 3, 7, 3))
    st = iso9283_statistics(x)
    for p in range(2):
        b = [x[p, d].mean(axis=0) for d in range(3)]
        vap = max(np.linalg.norm(b[i] - b[j]) for i in range(3) for j in range(3))
        assert st["vap_mm"][p] == pytest.approx(vap)
        for d in range(3):
            dist = np.linalg.norm(x[p, d] - b[d], axis=1)
            assert st["rp_mm"][p][d] == pytest.approx(dist.mean() + 3 * dist.std(ddof=1))
    with pytest.raises(ValueError, match="cycles >= 2"):
        iso9283_statistics(x[:, :, :1])


def test_histogram_bins_cover_every_value_and_shares_sum_to_one() -> None:
    rng = np.random.default_rng(2)
    a, b = rng.uniform(0.0, 0.76, 104), rng.uniform(0.0, 0.19, 104)
    h = histogram({"before": a, "after": b})
    edges = np.array(h["edges_mm"])
    assert edges[0] == 0.0 and edges[-1] >= a.max() and np.allclose(np.diff(edges), 0.05)
    assert sum(h["counts"]["before"]) == 104 and sum(h["counts"]["after"]) == 104
    assert sum(h["share"]["after"]) == pytest.approx(1.0)
    assert histogram({"x": np.array([0.3])}, width_mm=0.1)["counts"]["x"] == [0, 0, 1]


def test_visit_dirs_is_the_sign_of_each_axis_last_motion() -> None:
    a = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, -1.0], [2.0, 1.0, -1.0], [0.0, 1.0, -2.0]])
    expected = [[1, 1, 1], [1, 1, -1], [1, 1, -1], [-1, 1, -1]]
    assert visit_dirs(a, np.zeros(3)).tolist() == expected


def test_plan_is_seed_000s_layout_and_reproducible() -> None:
    scenario = load_scenario("kr210-cell")
    plan = TrialPlan(sizes=TrialSizes(n_sampling=12, n_targets=10))
    pts = plan_trial(scenario, plan)
    again = plan_trial(scenario, plan)
    assert np.array_equal(pts.targets.a_nominal_deg, again.targets.a_nominal_deg)
    cam = scenario.campaign
    for p in (pts.sampling, pts.targets):
        assert np.all(p.wanted_mm >= cam.box_min_mm - 1e-6) and np.all(p.wanted_mm <= cam.box_max_mm + 1e-6)
        assert np.all(np.abs(p.abc_deg) <= 10.0 + 1e-9)
        nominal = KinematicParams.from_robot(scenario.robot)
        fk = tcp_position_mm(nominal, axes_deg_to_q_rad(p.a_nominal_deg, nominal.sign))
        assert np.allclose(fk, p.wanted_mm, atol=1e-6)
        assert np.array_equal(p.dir, visit_dirs(p.a_nominal_deg, pts.home_deg))
    iso = pts.iso
    assert np.allclose(iso.points_mm[1], (cam.box_min_mm + cam.box_max_mm) / 2)  # P2: the box centre
    assert np.allclose(iso.starts_mm - iso.points_mm[:, None, :], 100.0 * np.eye(3)[None])
    assert FULL.n_sampling == 100 and FULL.n_targets == 104 and FULL.iso_cycles == 30
    assert FULL.chebyshev_order == 3 and QUICK.n_sampling + QUICK.n_targets >= 42
    with pytest.raises(ValueError, match="iso_cycles"):
        TrialSizes(iso_cycles=1)


def synthetic_result() -> TrialResult:
    rng = np.random.default_rng(3)
    n = 20
    wanted = rng.uniform(500.0, 1500.0, (n, 3))
    result = TrialResult(
        plan=TrialPlan(sizes=QUICK).to_dict(), started_at="2026-01-01T00:00:00Z", environment={}
    )
    for key, label, scale, feedback in (
        ("uncompensated", "uncompensated", 0.4, False),
        ("kinematic", "kinematic calibration", 0.2, False),
        ("chebyshev+feedback", "Chebyshev m=0 + joint feedback", 0.08, True),
    ):
        run = PointRun.empty(key, label, "targets", wanted, feedback=feedback)
        run.measured_mm[:] = wanted + rng.normal(0.0, scale, (n, 3))
        run.commanded_deg[:] = rng.uniform(-10, 10, (n, 6))
        run.state[:] = ["done" if feedback else "open"] * n
        result.runs[key] = run
    last = result.runs["chebyshev+feedback"]
    last.state[4], last.reason[4] = "failed", "not_settled: A2 (freeze)"
    last.measured_mm[4] = np.nan
    result.iso = {
        "points_mm": [[1800.0, 0.0, 900.0]],
        "cycles": 2,
        "approach_mm": 100.0,
        "warmup_cycles": 0,
        "repeatability_rated_mm": 0.06,
        "runs": {
            "without": {"stats": iso9283_statistics(rng.normal(0, 0.1, (1, 3, 2, 3)))},
            "with": {"stats": iso9283_statistics(rng.normal(0, 0.02, (1, 3, 2, 3)))},
        },
    }
    result.complete = True
    return result


def test_verdict_json_round_trip_and_reports() -> None:
    result = synthetic_result()
    v = verdict(result)
    assert v["ordering"]["mean"] and v["ordering"]["max"]
    assert result.table2()["chebyshev+feedback"]["n"] == 19  # the failed target is left out
    assert result.runs["chebyshev+feedback"].failures() == [
        {"index": 4, "state": "failed", "reason": "not_settled: A2 (freeze)"}
    ]
    back = TrialResult.from_dict(json.loads(result.to_json()))
    for key, st in result.table2().items():
        assert back.table2()[key]["3d"] == pytest.approx(st["3d"])
    assert np.isnan(back.runs["chebyshev+feedback"].measured_mm[4]).all()
    text = render_text(result)
    assert "Table 2" in text and "Ordering" in text and "0.76" in text
    page = render_html(result, command="comp-daemon trial --quick")
    assert (
        page.startswith("<!doctype html>")
        and "<script" not in page
        and "http://" not in page.replace('xmlns="http://www.w3.org/2000/svg"', "")
    )
    assert page.count("<svg") >= 6 and "not_settled" in page
    # a swapped ordering is reported as such
    result.runs["kinematic"].measured_mm[:] = result.runs["kinematic"].wanted_mm + 1.0
    assert not verdict(result)["ordering"]["mean"]
    with pytest.raises(ValueError, match="comp-daemon-trial"):
        TrialResult.from_dict({"format": "something else"})


def test_cli_renders_a_stored_result(tmp_path: Path) -> None:
    src = tmp_path / "trial.json"
    src.write_text(synthetic_result().to_json(), encoding="utf-8")
    out = tmp_path / "trial.html"
    proc = subprocess.run(
        [sys.executable, "-m", "comp_daemon", "trial", "--from-json", str(src), "--report", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Table 2" in proc.stdout and out.read_text(encoding="utf-8").startswith("<!doctype html>")
    bad = tmp_path / "bad.json"
    bad.write_text("[]", encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "comp_daemon", "trial", "--from-json", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and "not a trial result" in proc.stderr


def test_trial_phases_follow_the_sizes_in_the_documented_order() -> None:
    full = [name for name, _ in trial_phases(FULL)]
    assert full == [
        "grating calibration",
        "ISO 9283, robot alone",
        "sampling points, robot alone",
        "target points, uncompensated",
        "fits on the open-loop data (HTTP)",
        "target points, kinematic calibration",
        "ISO 9283, with joint feedback",
        "sampling points, with joint feedback",
        "target points, joint feedback only",
        "fits on the closed-loop data (HTTP)",
        "target points, Chebyshev m=3 + joint feedback",
        "target points, Chebyshev m=3 (seed 000 mapping) + joint feedback",
        "target points, kinematic + joint feedback",
    ]
    quick = [name for name, _ in trial_phases(QUICK)]
    assert quick == [
        *full[:7],
        "target points, Chebyshev m=0 + joint feedback",
        full[11].replace("m=3", "m=0"),
    ]
    # the kinematic model in the loop needs the closed-loop data
    no_loop = dataclasses.replace(FULL, loop_sampling=False, seed000_mapping=False)
    assert [name for name, _ in trial_phases(no_loop)] == [*full[:7], full[10]]
    assert len({phase for _, phase in trial_phases(FULL)}) == len(full)  # one step a phase
