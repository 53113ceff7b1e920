"""``poe:paper`` and the ballbar fit identify seed 002's 12 errors on the paper's own segment layout
(Table 1) where the robot is its IRB 120, and say so; the artifact keeps the layout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, write_dataset
from comp_daemon.instruments.ballbar_plan import TABLE5_ERRORS
from comp_daemon.kinematics.poe import irb120_table1, poe_tcp_position_mm
from comp_daemon.models.artifact import load_model
from comp_daemon.models.poe.calibration import LAYOUTS, paper_layout
from comp_daemon.models.poe.model import PoeErrorModel
from comp_daemon.models.registry import fit_model
from comp_daemon.robot.description import PRESETS, load_robot

IRB = load_robot("irb120")


def _table1_campaign(n: int = 80, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Axis values and TCPs of the IRB 120 as Table 1's chain with seed 002's Table 5 errors puts them."""
    lim = IRB.axis_limits_deg
    a = np.random.default_rng(seed).uniform(lim[:, 0] * 0.8, lim[:, 1] * 0.8, (n, 6))
    return a, poe_tcp_position_mm(irb120_table1(IRB), a, TABLE5_ERRORS)


def test_only_the_irb120_has_the_papers_layout() -> None:
    assert paper_layout(IRB) == "table1"
    assert [name for name in PRESETS if paper_layout(load_robot(name)) == "table1"] == ["irb120"]


def test_poe_paper_recovers_table1_errors_and_names_table1s_dependencies() -> None:
    a, p = _table1_campaign()
    fitted = fit_model("poe:paper", IRB, a[:60], p[:60], frame="base")
    assert fitted.info["layout"] == LAYOUTS["table1"]
    # Table 1's dependencies: dl5 moves the same points as dl6 (q4 along its own axis)
    removed = {r["name"]: r for r in fitted.info["identifiability"]["removed"]}
    assert removed["dl5"]["depends_on"] == ["dl6"]
    assert {"dl1", "dl2", "dtheta1", "dtheta6"} <= set(removed)
    assert fitted.info["identifiability"]["rank_svd"] == 13  # 7 errors and the base frame
    # the model of the paper's errors on the paper's layout: the held-out poses to 1e-6 mm
    assert np.abs(fitted.model.predict_tcp_mm(a[60:]) - p[60:]).max() < 1e-6


def test_the_artifact_keeps_the_layout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, p = _table1_campaign(120)
    data, out = tmp_path / "trk.csv", tmp_path / "paper.json"
    split = np.where(np.arange(120) % 3 == 0, "check", "fit")
    write_dataset(Dataset(a_deg=a, xyz_mm=p, split=split), data)
    assert main(["fit", str(data), "--robot", "irb120", "--model", "poe:paper", "--out", str(out)]) == 0
    assert "13 of 18 parameters identifiable" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["model"]["layout"] == "table1" and doc["fit"]["layout"] == LAYOUTS["table1"]
    loaded = load_model(out).model
    assert np.abs(loaded.predict_tcp_mm(a) - p).max() < 1e-6
    # an unknown layout, or Table 1's on another robot, is refused by name
    payload, frame = doc["model"], np.eye(4)
    with pytest.raises(ValueError, match="model field 'layout': expected one of robot, table1"):
        PoeErrorModel.from_payload(IRB, {**payload, "layout": "table2"}, None, frame)
    with pytest.raises(ValueError, match="'table1' is not a layout of the robot"):
        PoeErrorModel.from_payload(load_robot("kr210"), payload, None, frame)


def test_the_ballbar_fit_is_on_table1_and_says_so(tmp_path: Path) -> None:
    data, out = tmp_path / "bb.csv", tmp_path / "bb.json"
    assert (
        main(["sim", "sample", "--scenario", "ballbar", "--n", "3", "--seed", "1", "--out", str(data)]) == 0
    )
    assert main(["fit", str(data), "--robot", "irb120", "--model", "poe", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["model"]["layout"] == "table1" and doc["fit"]["layout"] == LAYOUTS["table1"]
    assert doc["fit"]["rank"] == 10  # dl5 and dl6 are one on Table 1's layout
