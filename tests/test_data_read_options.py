"""Files as exporters write them: ';'-separated, decimal commas, metres, radians, read with stated
options (ReadOptions; --delimiter, --decimal-comma, --units), and refused naming the option when
they look as if they needed one."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import DatasetError, read_dataset, read_dataset_json, write_dataset
from comp_daemon.data.options import ReadOptions, parse_units
from comp_daemon.data.table import Dataset
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")


def _campaign(n: int = 60) -> Dataset:
    lim = KR.axis_limits_deg
    rng = np.random.default_rng(0)
    a = rng.uniform(lim[:, 0] * 0.5 + lim[:, 1] * 0.5 - 40, lim[:, 0] * 0.5 + lim[:, 1] * 0.5 + 40, (n, 6))
    xyz = tcp_position_mm(KinematicParams.from_robot(KR), axes_deg_to_q_rad(a, KR.sign))
    split = np.where(np.arange(n) % 4 == 0, "check", "fit")
    return Dataset(a_deg=a, xyz_mm=xyz, split=split)


def _exported(
    data: Dataset, sep: str = ";", comma: bool = True, metres: bool = True, radians: bool = True
) -> str:
    """The data set as a spreadsheet exporter writes it."""
    assert data.a_deg is not None and data.xyz_mm is not None and data.split is not None

    def num(v: float) -> str:
        text = repr(float(v))
        return text.replace(".", ",") if comma else text

    a = np.radians(data.a_deg) if radians else data.a_deg
    xyz = data.xyz_mm / 1000.0 if metres else data.xyz_mm
    lines = [sep.join(["a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z", "split"])]
    for i in range(len(data)):
        lines.append(sep.join([*(num(v) for v in a[i]), *(num(v) for v in xyz[i]), str(data.split[i])]))
    return "\n".join(lines) + "\n"


def _same(a: Dataset, b: Dataset) -> None:
    assert a.a_deg is not None and b.a_deg is not None and a.xyz_mm is not None and b.xyz_mm is not None
    assert np.max(np.abs(a.a_deg - b.a_deg)) < 1e-9
    assert np.max(np.abs(a.xyz_mm - b.xyz_mm)) < 1e-9
    assert a.split is not None and b.split is not None and list(a.split) == list(b.split)


def test_european_export_in_metres_and_radians_reads_with_stated_options() -> None:
    data = _campaign()
    text = _exported(data)
    options = ReadOptions.of(decimal_comma=True, units="m,rad")
    _same(read_dataset(text, limits_deg=KR.axis_limits_deg, options=options), data)
    # ';' with '.' decimals, tab-separated, in mm and deg: each by its own option
    _same(read_dataset(_exported(data, comma=False), options=ReadOptions.of(";", units="m,rad")), data)
    tabbed = _exported(data, sep="\t", metres=False, radians=False)
    _same(read_dataset(tabbed, options=ReadOptions.of("tab", decimal_comma=True)), data)


def test_json_records_in_metres_read_with_units() -> None:
    data = _campaign(10)
    assert data.a_deg is not None and data.xyz_mm is not None
    records = [
        {
            **{f"a{j + 1}": float(data.a_deg[i, j]) for j in range(6)},
            **dict(zip("xyz", (data.xyz_mm[i] / 1000).tolist(), strict=True)),
        }
        for i in range(len(data))
    ]
    got = read_dataset_json(json.dumps(records), options=ReadOptions.of(units="m,deg"))
    assert got.xyz_mm is not None and np.max(np.abs(got.xyz_mm - data.xyz_mm)) < 1e-9
    with pytest.raises(DatasetError, match="apply to CSV files"):
        read_dataset_json(json.dumps(records), options=ReadOptions.of(decimal_comma=True))


@pytest.mark.parametrize(
    ("kwargs", "options", "match", "row", "column"),
    [
        # ';'-separated, read as the format says: the header is one field
        ({}, ReadOptions(), "one column holding semicolons; .* read the file with --delimiter ';'", 1, None),
        # decimal commas in a ';' file read with --delimiter ';' only
        (
            {},
            ReadOptions.of(";", units="m,rad"),
            "has a decimal comma; read the file with --decimal-comma",
            2,
            "a1",
        ),
        # radians read as degrees
        (
            {"comma": False, "sep": ",", "metres": False},
            ReadOptions(),
            "radians\\? .*--units mm,rad",
            None,
            "a1",
        ),
    ],
)
def test_files_that_need_an_option_are_refused_naming_it(
    kwargs: dict, options: ReadOptions, match: str, row: int | None, column: str | None
) -> None:
    with pytest.raises(DatasetError, match=match) as caught:
        read_dataset(_exported(_campaign(), **kwargs), options=options)
    assert (caught.value.row, caught.value.column) == (row, column)


def test_a_quoted_decimal_comma_in_a_comma_file_names_the_option() -> None:
    text = 'a1,a2,a3,a4,a5,a6,x,y,z\n0,-90,90,0,10,0,"1200,5",0,1500\n'
    with pytest.raises(
        DatasetError, match="'1200,5' has a decimal comma; read the file with --decimal-comma"
    ):
        read_dataset(text)


def test_stated_units_turn_the_guess_off() -> None:
    """A campaign really in degrees near zero on every axis: refused as radians-looking until
    --units mm,deg says what the numbers are."""
    data = _campaign()
    assert data.a_deg is not None
    near_zero = (data.a_deg - data.a_deg.mean(axis=0)) / 10.0
    a_deg = np.clip(near_zero, -6.0, 6.0)  # every axis within ±6°
    local = Dataset(a_deg=a_deg, xyz_mm=data.xyz_mm, split=data.split)
    text = _exported(local, sep=",", comma=False, metres=False, radians=False)
    with pytest.raises(DatasetError, match="--units mm,rad"):
        read_dataset(text)
    got = read_dataset(text, options=ReadOptions.of(units="mm,deg"))
    assert got.a_deg is not None and np.max(np.abs(got.a_deg - a_deg)) < 1e-12


def test_metres_are_refused_by_the_fit_naming_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The reader cannot know a robot's size; the fit's scale check does, and names --units."""
    metres = tmp_path / "metres.csv"
    metres.write_text(_exported(_campaign(), sep=",", comma=False, radians=False), "utf-8")
    out = tmp_path / "m.json"
    assert main(["fit", str(metres), "--robot", "kr210", "--model", "nominal", "--out", str(out)]) == 2
    assert "(in metres?); a file in metres is read with --units m,deg" in capsys.readouterr().err
    assert (
        main(
            [
                "fit",
                str(metres),
                "--robot",
                "kr210",
                "--model",
                "nominal",
                "--out",
                str(out),
                "--units",
                "m,deg",
            ]
        )
        == 0
    )


def test_a_dot_under_decimal_comma_is_refused() -> None:
    text = "a1;a2;a3;a4;a5;a6;x;y;z\n0;-90;90;0;10;0;1200,5;0;1500\n0;-80;90;0;10;0;1.200;0;1500\n"
    with pytest.raises(
        DatasetError, match=re.escape("'1.200' has a '.', read with --decimal-comma")
    ) as caught:
        read_dataset(text, options=ReadOptions.of(decimal_comma=True))
    assert (caught.value.row, caught.value.column) == (3, "x")
    with pytest.raises(DatasetError, match=re.escape("not a number: '1.200,5'")):
        read_dataset(text.replace("1.200", "1.200,5"), options=ReadOptions.of(decimal_comma=True))


def test_option_errors() -> None:
    assert parse_units("rad, m") == ("m", "rad")
    for bad in ("m", "m,rad,deg", "in,deg", "mm,mm"):
        with pytest.raises(ValueError, match="--units"):
            parse_units(bad)
    with pytest.raises(ValueError, match="--decimal-comma with ','"):
        ReadOptions.of(",", decimal_comma=True)
    with pytest.raises(ValueError, match=re.escape("--delimiter '|'")):
        ReadOptions.of("|")


def test_commands_take_the_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = _campaign()
    plain, european = tmp_path / "plain.csv", tmp_path / "european.csv"
    write_dataset(data, plain)
    european.write_text(_exported(data), "utf-8")
    assert main(["data", "check", str(european), "--robot", "kr210"]) == 2
    assert "--delimiter ';'" in capsys.readouterr().err
    assert (
        main(["data", "check", str(european), "--robot", "kr210", "--decimal-comma", "--units", "m,rad"]) == 0
    )
    summary = json.loads(capsys.readouterr().out)
    assert summary["read_as"] == "fields by ';', decimal mark ',', lengths in m, angles in rad"
    assert summary["rows"] == len(data)
    models = []
    for path, extra in ((plain, []), (european, ["--decimal-comma", "--units", "m,rad"])):
        out = tmp_path / f"{path.stem}.json"
        assert (
            main(["fit", str(path), "--robot", "kr210", "--model", "kinematic", "--out", str(out), *extra])
            == 0
        )
        models.append(json.loads(out.read_text("utf-8")))
    # the same numbers fitted: the same fit (to the last bits of the unit conversions)
    assert models[0]["fit"]["rms_mm"] == pytest.approx(models[1]["fit"]["rms_mm"], abs=1e-6)
    assert not math.isnan(models[1]["fit"]["rms_mm"])
