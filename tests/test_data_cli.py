"""``comp-daemon data check``: a JSON summary and exit 0, or the row and column and exit 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, write_dataset

REPO = Path(__file__).resolve().parents[1]


def campaign(n: int = 20) -> Dataset:
    rng = np.random.default_rng(3)
    a_deg = np.column_stack(
        [rng.uniform(-30, 30, n), rng.uniform(-100, -60, n), rng.uniform(60, 110, n), np.zeros((n, 3))]
    )
    return Dataset(
        a_deg=a_deg,
        xyz_mm=rng.uniform(-1500, 1500, (n, 3)),
        dir=rng.choice(np.array([-1, 1], dtype=np.int8), (n, 6)),
        payload_kg=np.where(np.arange(n) % 2 == 0, 0.0, 120.0),
    )


@pytest.fixture()
def good_file(tmp_path: Path) -> Path:
    path = tmp_path / "campaign.csv"
    write_dataset(campaign(), path)
    return path


@pytest.fixture()
def bad_file(tmp_path: Path, good_file: Path) -> Path:
    lines = good_file.read_text("utf-8").splitlines()
    cells = lines[5].split(",")
    cells[1] = "10.0"  # a2 above the KR210's -5 deg limit, on row 6
    lines[5] = ",".join(cells)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_check_good_file(good_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "check", str(good_file), "--robot", "kr210"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["ok"] is True
    assert summary["rows"] == 20
    assert summary["columns"][:9] == ["a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z"]
    assert summary["dir"] is True
    assert summary["payloads_kg"] == [0.0, 120.0]
    assert summary["split"]["column"] is False
    assert summary["split"]["drawn"]["fit"] + summary["split"]["drawn"]["check"] == 20
    assert summary["split"]["drawn"]["check"] == 4
    expected = campaign()
    assert expected.a_deg is not None
    assert summary["axis_range_deg"]["a2"] == [expected.a_deg[:, 1].min(), expected.a_deg[:, 1].max()]
    assert summary["content_sha256"] == expected.content_sha256


def test_check_bad_file(bad_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "check", str(bad_file), "--robot", "kr210"]) == 2
    captured = capsys.readouterr()
    refusal = json.loads(captured.out)
    assert refusal["ok"] is False
    assert (refusal["row"], refusal["column"]) == (6, "a2")
    assert "row 6, column 'a2'" in captured.err
    assert "outside the axis limits" in captured.err


def test_check_json_records_and_min_rows(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    records = [
        {"a1": 0, "a2": -90, "a3": 90, "a4": 0, "a5": 30, "a6": 0, "x": 1.5, "y": 2.0, "z": 3.0, "split": s}
        for s in ("fit", "fit", "check")
    ]
    path = tmp_path / "upload.json"
    path.write_text(json.dumps(records), encoding="utf-8")
    assert main(["data", "check", str(path), "--robot", "kr210"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["split"] == {"column": True, "fit": 2, "check": 1}
    assert main(["data", "check", str(path), "--robot", "kr210", "--min-rows", "39"]) == 2
    assert "fewer rows than the chosen model has parameters (39)" in capsys.readouterr().err


def test_check_targets_kind(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "targets.csv"
    path.write_text("tx,ty,tz,ta,tb,tc\n1500,0,1700,180,0,180\n", encoding="utf-8")
    assert main(["data", "check", str(path), "--robot", "kr210"]) == 2
    assert "column 'a1'" in capsys.readouterr().err
    assert main(["data", "check", str(path), "--robot", "kr210", "--kind", "targets"]) == 0
    assert json.loads(capsys.readouterr().out)["pose_targets"] is True


def test_check_unknown_robot_and_missing_file(good_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "check", str(good_file), "--robot", "nosuchrobot"]) == 2
    assert "nosuchrobot" in capsys.readouterr().err
    assert main(["data", "check", str(good_file.with_name("absent.csv")), "--robot", "kr210"]) == 2
    assert "absent.csv" in capsys.readouterr().err


def test_check_via_python_dash_m(good_file: Path, bad_file: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    good = subprocess.run(
        [sys.executable, "-m", "comp_daemon", "data", "check", str(good_file), "--robot", "kr210"],
        capture_output=True,
        text=True,
        env=env,
        check=False,
        timeout=60,
    )
    assert good.returncode == 0, good.stderr
    assert json.loads(good.stdout)["rows"] == 20
    bad = subprocess.run(
        [sys.executable, "-m", "comp_daemon", "data", "check", str(bad_file), "--robot", "kr210"],
        capture_output=True,
        text=True,
        env=env,
        check=False,
        timeout=60,
    )
    assert bad.returncode == 2
    assert "row 6, column 'a2'" in bad.stderr
