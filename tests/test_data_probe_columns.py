"""The data set's station, 6-DOF probe orientation (qw, qx, qy, qz) and per-row sigma_mm columns:
parsed, refused by row and column, carried on the Dataset, written back, and reported by
``data check``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, DatasetError, read_dataset, read_dataset_json, write_dataset
from comp_daemon.data.options import ReadOptions
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.robot.description import load_robot

HEAD = "a1,a2,a3,a4,a5,a6,x,y,z,station,qw,qx,qy,qz,sigma_mm"


def _row(i: int, station: str = "A", q: tuple[float, ...] | None = None, sigma: str = "0.01") -> str:
    angle = math.radians(10.0 * i)
    q = q or (math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0)
    quat = ",".join(repr(v) for v in q)
    return f"{5 * i},-90,{90 + i},0,{10 + i},0,{1500 + i},{20 * i},{1200 - i},{station},{quat},{sigma}"


def _text(rows: list[str], head: str = HEAD) -> str:
    return "\n".join([head, *rows]) + "\n"


def test_columns_are_carried_and_written_back(tmp_path: Path) -> None:
    rows = [
        _row(i, "before move" if i < 4 else "after move", sigma=f"{0.005 * (1 + i % 3)}") for i in range(8)
    ]
    data = read_dataset(_text(rows))
    assert data.station == ("before move",) * 4 + ("after move",) * 4
    assert data.probe_q_wxyz is not None and data.probe_q_wxyz.shape == (8, 4)
    assert np.allclose(np.linalg.norm(data.probe_q_wxyz, axis=1), 1.0)
    assert data.sigma_mm is not None and data.sigma_mm.tolist() == pytest.approx(
        [0.005, 0.01, 0.015] * 2 + [0.005, 0.01]
    )
    assert not data.extra  # known columns, not kept as text
    path = tmp_path / "out.csv"
    write_dataset(data, path)
    again = read_dataset(path)
    assert again == data and again.station == data.station
    part = data.subset([1, 6])
    assert part.station == ("before move", "after move") and part.sigma_mm is not None
    assert part.probe_q_wxyz is not None and np.array_equal(part.probe_q_wxyz, data.probe_q_wxyz[[1, 6]])
    summary = data.summary()
    assert summary["stations"] == {"after move": 4, "before move": 4}
    assert summary["probe_orientation"] is True
    assert summary["sigma_mm"] == {"min": 0.005, "median": 0.01, "max": 0.015}


def _nominal_row(i: int, station: str) -> str:
    """A row whose position is the KR 210's nominal TCP at its axis values (data check applies the
    millimetre rule to the positions)."""
    robot = load_robot("kr210")
    a_deg = np.array([5 * i, -90, 90 + i, 0, 10 + i, 0], dtype=float)
    x, y, z = tcp_position_mm(KinematicParams.from_robot(robot), np.radians(a_deg)[None])[0]
    fields = _row(i, station).split(",")
    head, tail = fields[:6], fields[9:]
    return ",".join([*head, repr(float(x)), repr(float(y)), repr(float(z)), *tail])


def test_data_check_reports_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "probe.csv"
    path.write_text(_text([_nominal_row(i, "S1" if i % 2 else "S2") for i in range(6)]), "utf-8")
    assert main(["data", "check", str(path), "--robot", "kr210"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stations"] == {"S1": 3, "S2": 3} and out["probe_orientation"] is True
    assert out["sigma_mm"]["median"] == 0.01


@pytest.mark.parametrize(
    ("rows", "head", "match", "row", "column"),
    [
        (
            [_row(0), _row(1), _row(2, q=(0.9, 0.0, 0.1, 0.0))],
            HEAD,
            "has norm 0.905539; a unit quaternion",
            4,
            "qw",
        ),
        ([_row(0), _row(1, sigma="0")], HEAD, "sigma_mm must be > 0 mm", 3, "sigma_mm"),
        ([_row(0), _row(1, sigma="-0.01")], HEAD, "sigma_mm must be > 0 mm", 3, "sigma_mm"),
        ([_row(0), _row(1, sigma="n/a")], HEAD, "not a number: 'n/a'", 3, "sigma_mm"),
        ([_row(0), _row(1, station=" ")], HEAD, "empty station", 3, "station"),
        ([_row(0)[: _row(0).rindex(",0.0,")]], HEAD.replace(",qz,sigma_mm", ""), "column missing", 1, "qz"),
    ],
)
def test_bad_cells_are_refused_by_row_and_column(
    rows: list[str], head: str, match: str, row: int, column: str
) -> None:
    with pytest.raises(DatasetError, match=match) as caught:
        read_dataset(_text(rows, head))
    assert (caught.value.row, caught.value.column) == (row, column)


def test_an_orientation_needs_the_probe_position() -> None:
    text = "a1,a2,a3,a4,a5,a6,qw,qx,qy,qz\n0,-90,90,0,10,0,1,0,0,0\n"
    with pytest.raises(DatasetError, match="needs its position x, y, z") as caught:
        read_dataset(text, kind="targets")
    assert caught.value.column == "x"
    with pytest.raises(ValueError, match="needs its position"):
        Dataset(a_deg=np.zeros((1, 6)), probe_q_wxyz=np.array([[1.0, 0, 0, 0]]))


def test_json_records_and_units() -> None:
    records = [
        {
            "a1": 0,
            "a2": -90,
            "a3": 90,
            "a4": 0,
            "a5": 10 + i,
            "a6": 0,
            "x": 1.5,
            "y": 0.1 * i,
            "z": 1.2,
            "station": 7,
            "sigma_mm": 0.00002,
        }
        for i in range(4)
    ]
    data = read_dataset_json(json.dumps(records), options=ReadOptions.of(units="m,deg"))
    assert data.station == ("7",) * 4
    assert data.sigma_mm is not None and data.sigma_mm == pytest.approx([0.02] * 4)
    records[2]["station"] = [1]
    with pytest.raises(DatasetError, match="station must be a string or an integer") as caught:
        read_dataset_json(json.dumps(records))
    assert (caught.value.row, caught.value.column) == (3, "station")
