"""``comp-daemon evaluate --solvers``: LM and the metaheuristics of seed 002 on one ballbar
identification problem, one row per run with the spec's columns (acceptance check 7)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.ballbar import ballbar_dataset
from comp_daemon.data.dataset import dataset_to_csv
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, ballbar_lengths_mm
from comp_daemon.instruments.ballbar_plan import TABLE5_ERRORS, ballbar_plan
from comp_daemon.instruments.solver_comparison import (
    compare_solvers,
    parse_solvers,
    solver_table,
    spec_default_problem,
)
from comp_daemon.kinematics.poe import irb120_table1
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")


def test_parse_solvers_refuses_unknown_and_repeated_names() -> None:
    assert parse_solvers("lm, IMFO,woa") == ["lm", "imfo", "woa"]
    for bad in ("", "lm,ga", "lm,lm"):
        with pytest.raises(ValueError, match="--solvers"):
            parse_solvers(bad)


def test_compare_on_the_spec_default_problem_has_a_row_per_run_and_lm_wins() -> None:
    problem = spec_default_problem(ROBOT)
    runs = compare_solvers(problem, ["lm", "imfo", "woa"], agents=20, max_iter=20, seeds=[0, 1])
    assert [r.solver.split()[0] for r in runs] == ["lm", "imfo", "imfo", "woa", "woa"]
    lm = runs[0]
    assert lm.rank == 9 and lm.rows == 103 and lm.noise_mm == 0.0
    assert lm.final_h_mm < 1e-3 and lm.reached and lm.held_out_h_mm is not None
    for r in runs[1:]:
        assert r.evaluations == 20 * r.iterations and r.iterations <= 20
        assert r.final_h_mm > lm.final_h_mm and r.max_diff_from_lm > 0
    lines = solver_table(runs)
    assert len(lines) == 2 + len(runs)
    head = lines[0]
    for column in ("rows f", "rank", "noise σ", "solver", "K_max", "evaluations", "final H", "held-out H"):
        assert column in head
    assert "42.46" not in "\n".join(lines) and "62.03" not in "\n".join(lines)


def test_evaluate_solvers_cli_on_a_ballbar_campaign(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = ballbar_plan(ROBOT, 4)
    truth = np.concatenate([TABLE5_ERRORS, [0.8, -0.6, 0.5]])
    bar = ballbar_lengths_mm(irb120_table1(ROBOT), plan.a_deg, truth, PAPER_PIVOT_MM)
    data = tmp_path / "bb.csv"
    data.write_text(dataset_to_csv(ballbar_dataset(plan.a_deg, plan.arc, PAPER_PIVOT_MM, bar_mm=bar)))
    out = tmp_path / "runs.json"
    argv = ["evaluate", str(data), "--robot", "irb120", "--solvers", "lm,mfo", "--agents", "10"]
    argv += ["--iterations", "10", "--solver-seeds", "3", "--json", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "held out" in text  # four arcs, no split: one drawn
    rows = [line for line in text.splitlines() if line.startswith("| bb.csv")]
    assert len(rows) == 2 and "| mfo | 10 | 10 | 3 |" in rows[1]
    doc = json.loads(out.read_text())
    lm, mfo = doc["runs"]
    assert lm["final_h_mm"] < 1e-6 and lm["held_out_h_mm"] < 1e-6  # noise-free, the model's own form
    assert mfo["seed"] == 3 and mfo["agents"] == 10


def test_evaluate_solvers_refuses_a_tracker_data_set(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "trk.csv"
    data.write_text("a1,a2,a3,a4,a5,a6,x,y,z\n" + "0,0,0,0,90,0,1,2,3\n" * 20)
    assert main(["evaluate", str(data), "--robot", "irb120", "--solvers", "lm"]) != 0
    assert "not a ballbar campaign" in capsys.readouterr().err
