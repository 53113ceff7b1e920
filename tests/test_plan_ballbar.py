"""``comp-daemon plan ballbar``: the poses of a ballbar campaign, and what the choice rests on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.ballbar import ballbar_dataset, read_ballbar
from comp_daemon.data.bars import read_table
from comp_daemon.data.dataset import dataset_to_csv
from comp_daemon.instruments.ballbar_plan import arc_count_rates, ballbar_plan
from comp_daemon.kinematics.forward import flange_pose, tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")


def test_plan_writes_the_arcs_on_the_pivot_sphere(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "plan.csv"
    assert main(["plan", "ballbar", "--robot", "irb120", "--arcs", "4", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "variogram" in text and "<- neighbouring points of an arc" in text
    assert "2 arcs: mean" in text and "4 arcs: mean" in text and "smallest variance rate" in text
    plan = read_table(out, limits_deg=ROBOT.axis_limits_deg)
    assert "bar_mm" not in plan.extra and plan.a_deg is not None
    arcs = np.array([int(v) for v in plan.extra["arc"]])
    assert [int((arcs == k).sum()) for k in (1, 2, 3, 4)] == [37, 33, 33, 25]
    params = KinematicParams.from_robot(ROBOT)
    tcp = tcp_position_mm(params, axes_deg_to_q_rad(plan.a_deg, params.sign))
    pivot = np.array([float(plan.extra[c][0]) for c in ("cx", "cy", "cz")])
    np.testing.assert_allclose(pivot, [350.0, 0.0, 394.0])
    assert np.abs(np.linalg.norm(tcp - pivot, axis=1) - 100.0).max() < 1e-6
    # one fixed flange orientation per arc, a different one on each
    rot = flange_pose(params, axes_deg_to_q_rad(plan.a_deg, params.sign))[:, :3, :3]
    first = [rot[np.flatnonzero(arcs == k)[0]] for k in (1, 2, 3)]
    for k in (1, 2, 3):
        assert np.abs(rot[arcs == k] - first[k - 1]).max() < 1e-8
    assert np.abs(first[0] - first[1]).max() > 0.1 and np.abs(first[1] - first[2]).max() > 0.1
    # filled in with readings, the plan is a ballbar campaign
    campaign = read_ballbar(
        dataset_to_csv(ballbar_dataset(plan.a_deg, arcs, pivot, bar_mm=np.linalg.norm(tcp - pivot, axis=1)))
    )
    assert len(campaign) == 128


def test_plan_options_and_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "p.csv"
    assert (
        main(
            [
                "plan",
                "ballbar",
                "--robot",
                "irb120",
                "--arcs",
                "2",
                "--step",
                "10",
                "--orientation",
                "vertical",
                "--pivot",
                "350,0,400",
                "--radius",
                "90",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    plan = read_table(out)
    assert len(plan) == 19 + 17 and plan.extra["cz"][0] == "400.0"
    assert main(["plan", "ballbar", "--robot", "irb120", "--arcs", "9", "--out", str(out)]) == 2
    assert "--arcs: 1..6" in capsys.readouterr().err
    assert main(["plan", "ballbar", "--robot", "irb120", "--pivot", "1200,0,0", "--out", str(out)]) == 2
    assert "not reachable" in capsys.readouterr().err


def test_arc_count_rates_and_the_vertical_plan() -> None:
    rates = arc_count_rates(ROBOT, seed=0)
    assert rates.arcs == (2, 3, 4) and all(0 <= r for r in rates.variance_rate)
    assert rates.variance_rate[1] < rates.variance_rate[0]  # a third arc brings the spread closer
    vertical = ballbar_plan(ROBOT, 3, orientation="vertical")
    assert len(vertical.a_deg) == 103 and np.abs(vertical.a_deg[:, 3]).max() < 1e-6  # A4 ≡ 0
