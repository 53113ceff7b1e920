"""``compensate`` on a program with bad rows: the good rows are compensated, each refused row is
listed with its row in the file and what is wrong, and the exit status says which happened
(0 every row, 3 some refused, 2 none compensated or the file itself refused)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.commands.compensate import SOME_REFUSED
from comp_daemon.data.dataset import Dataset, read_dataset, write_dataset
from comp_daemon.data.rowwise import read_rows
from comp_daemon.kinematics.params import PARAM_NAMES, KinematicParams
from comp_daemon.models.artifact import save_model
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")
AXES = ("a1", "a2", "a3", "a4", "a5", "a6")
SINGULAR = (0.0, -90.0, 90.0, 0.0, 0.0, 0.0)  # A5 = 0: axes 4 and 6 in line


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(7)
    scale = np.array(
        [2e-4 if n.startswith(("theta", "alpha", "beta", "base_r")) else 0.3 for n in PARAM_NAMES]
    )
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=len(PARAM_NAMES)) * scale)
    path = tmp_path_factory.mktemp("model") / "kin.json"
    save_model(KinematicModel(KR, truth), path, data_sha256="0" * 64, frame="base")
    return path


def program(n: int) -> np.ndarray:
    a = np.random.default_rng(5).uniform([-40, -110, 60, -60, 30, -60], [40, -60, 130, 60, 90, 60], (n, 6))
    return a


def write_program(path: Path, rows: list[list[str]]) -> Path:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow([*AXES, "pose_id"])
        writer.writerows(rows)
    return path


def test_a_thousand_hole_program_with_bad_rows_compensates_the_others(
    model_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rows = [[repr(float(v)) for v in a] + [f"hole-{k + 1}"] for k, a in enumerate(program(1000))]
    rows[9][1] = "10.0"  # file row 11: a2 above the KR210's -5 deg limit
    rows[249][2] = "abc"  # row 251: not a number
    rows[500][:6] = [repr(v) for v in SINGULAR]  # row 502: at the wrist singularity
    rows[801] = rows[801][:4]  # row 803: fields missing
    path = write_program(tmp_path / "program.csv", rows)
    out, refused = tmp_path / "out.csv", tmp_path / "refused.csv"
    status = main(["compensate", str(model_path), str(path), "--out", str(out), "--refused", str(refused)])
    assert status == SOME_REFUSED == 3
    captured = capsys.readouterr()
    assert "996 targets compensated" in captured.out and "4 refused" in captured.out
    listed = [line for line in captured.err.splitlines() if "refused row" in line]
    assert len(listed) == 4
    assert "refused row 11, column 'a2': " in listed[0] and "-5" in listed[0]
    assert "refused row 251, column 'a3': " in listed[1]
    assert "refused row 502: near wrist singularity: A5 = 0.0°" in listed[2]
    assert "refused row 803: 4 fields, but the header has 7 columns" in listed[3]
    with refused.open(newline="") as fh:
        table = list(csv.DictReader(fh))
    assert [(r["row"], r["column"]) for r in table] == [("11", "a2"), ("251", "a3"), ("502", ""), ("803", "")]
    done = read_dataset(out, kind="targets")
    assert len(done) == 996
    kept = [int(v) for v in done.extra["target_row"]]
    assert sorted(set(range(2, 1002)) - set(kept)) == [11, 251, 502, 803]
    # each compensated row is the one of its source row
    assert done.pose_id is not None
    assert [p for p in done.pose_id] == [f"hole-{r - 1}" for r in kept]


def test_exit_status_tells_all_some_or_none(
    model_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = [[repr(float(v)) for v in a] + [""] for a in program(5)]
    out = tmp_path / "out.csv"
    assert (
        main(["compensate", str(model_path), str(write_program(tmp_path / "g.csv", good)), "--out", str(out)])
        == 0
    )
    assert "refused" not in capsys.readouterr().err
    bad = [[*r[:1], "10.0", *r[2:]] for r in good]
    out.unlink()
    assert (
        main(["compensate", str(model_path), str(write_program(tmp_path / "b.csv", bad)), "--out", str(out)])
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("refused row") == 5 and "no target could be compensated (5 refused)" in err
    assert not out.exists()
    # a fault of the file, not of a row, still refuses the file
    (tmp_path / "h.csv").write_text("a1,a2,a3,a4,a5\n0,-90,90,0,30\n")
    assert main(["compensate", str(model_path), str(tmp_path / "h.csv"), "--out", str(out)]) == 2
    assert "refused row" not in capsys.readouterr().err


def test_json_targets_refuse_by_record_and_unreachable_tcps_by_row(
    model_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    records = [{"tx": 1800.0 + 10 * k, "ty": 100.0 * k, "tz": 1200.0} for k in range(6)]
    records[2]["tx"] = "far"  # record 3: a string, not a number
    records[4]["tx"] = 9.0e4  # record 5: 90 m away
    path = tmp_path / "targets.json"
    path.write_text(json.dumps(records))
    read = read_rows(path, limits_deg=KR.axis_limits_deg)
    assert [(r.row, r.column, r.row_label) for r in read.refused] == [(3, "tx", "record")]
    assert read.dataset is not None and list(read.dataset.row_numbers) == [1, 2, 4, 5, 6]
    out = tmp_path / "out.csv"
    assert main(["compensate", str(model_path), str(path), "--out", str(out)]) == SOME_REFUSED
    err = capsys.readouterr().err
    assert "refused record 3, column 'tx'" in err
    assert "refused record 5: unreachable within joint limits" in err
    assert [int(v) for v in read_dataset(out, kind="targets").extra["target_row"]] == [1, 2, 4, 6]


def test_a_clean_file_reads_as_the_reader_reads_it(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    write_dataset(Dataset(a_deg=program(7)), path)
    read = read_rows(path, limits_deg=KR.axis_limits_deg)
    assert read.refused == () and read.dataset == read_dataset(path, kind="targets")
