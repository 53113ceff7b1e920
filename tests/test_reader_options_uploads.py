"""The reader options (separator, decimal comma, units, Euler angles) on ballbar and cross-bar
campaign files (command line and readers) and on HTTP uploads (query parameters or form fields),
validated there with the command line's sentences."""

from __future__ import annotations

import math
from pathlib import Path

import httpx
import numpy as np
import pytest
from test_ballbar_campaign import client
from test_service_api import auth

from comp_daemon.cli import main
from comp_daemon.data.ballbar import ballbar_dataset, read_ballbar
from comp_daemon.data.crossbar import read_crossbar
from comp_daemon.data.dataset import dataset_to_csv
from comp_daemon.data.options import ReadOptions
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, ballbar_lengths_mm
from comp_daemon.instruments.ballbar_plan import TABLE5_ERRORS, ballbar_plan
from comp_daemon.kinematics.poe import irb120_table1
from comp_daemon.preparation.pipeline import nominal_tcp
from comp_daemon.robot.description import load_robot

IRB = load_robot("irb120")
PLAN = ballbar_plan(IRB, 3)
TRUTH = np.concatenate([TABLE5_ERRORS, [0.8, -0.6, 0.5]])
LENGTHS = ("bar_mm", "cx", "cy", "cz", "bar_l_mm", "x", "y", "z")
ANGLES = ("a1", "a2", "a3", "a4", "a5", "a6")
EUROPEAN = ReadOptions.of(decimal_comma=True, units="m,rad")
FIXTURES = (client,)  # the service of an IRB 120, as the ballbar campaign tests use it
AXES = {"a1": 10.0, "a2": 20.0, "a3": -15.0, "a4": 5.0, "a5": 40.0, "a6": 0.0}  # an IRB 120 pose


def _ballbar_csv() -> str:
    bar = ballbar_lengths_mm(irb120_table1(IRB), PLAN.a_deg, TRUTH, PAPER_PIVOT_MM)
    return dataset_to_csv(ballbar_dataset(PLAN.a_deg, PLAN.arc, PAPER_PIVOT_MM, bar_mm=bar))


def _european(text: str) -> str:
    """``text`` as a spreadsheet writes it: ';', decimal commas, metres and radians."""
    lines = text.splitlines()
    header = lines[0].split(",")
    out = [";".join(header)]
    for line in lines[1:]:
        cells = []
        for name, cell in zip(header, line.split(","), strict=True):
            if name in LENGTHS and cell:
                cell = repr(float(cell) / 1000.0)
            elif name in ANGLES:
                cell = repr(math.radians(float(cell)))
            cells.append(cell.replace(".", ","))
        out.append(";".join(cells))
    return "\n".join(out) + "\n"


def test_a_european_ballbar_export_reads_to_the_same_campaign() -> None:
    plain = read_ballbar(_ballbar_csv(), tcp_mm=nominal_tcp(IRB), limits_deg=IRB.axis_limits_deg)
    text = _european(_ballbar_csv())
    read = read_ballbar(text, tcp_mm=nominal_tcp(IRB), limits_deg=IRB.axis_limits_deg, options=EUROPEAN)
    assert np.max(np.abs(read.bar_mm - plain.bar_mm)) < 1e-9
    assert np.max(np.abs(read.pivot_mm - plain.pivot_mm)) < 1e-9
    assert np.max(np.abs(read.a_deg - plain.a_deg)) < 1e-9
    assert np.array_equal(read.arc, plain.arc)


def test_a_european_crossbar_export_reads_to_the_same_campaign(tmp_path: Path) -> None:
    path = tmp_path / "cb.csv"
    assert main(["sim", "sample", "--scenario", "crossbar", "--robot", "motoman_mh6", "--n", "14",
                 "--seed", "1", "--out", str(path)]) == 0  # fmt: skip
    plain = read_crossbar(path)
    read = read_crossbar(_european(path.read_text()), options=EUROPEAN)
    assert np.max(np.abs(read.bar_l_mm - plain.bar_l_mm)) < 1e-9
    assert np.max(np.abs(read.rows.a_deg - plain.rows.a_deg)) < 1e-9  # type: ignore[operator]
    assert np.array_equal(read.socket, plain.socket) and np.array_equal(read.placement, plain.placement)


def test_the_fit_of_a_european_ballbar_file_equals_the_plain_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plain, european = tmp_path / "bb.csv", tmp_path / "bb-eu.csv"
    plain.write_text(_ballbar_csv())
    european.write_text(_european(_ballbar_csv()))
    fit = ["fit", "--robot", "irb120", "--model", "poe", "--out", str(tmp_path / "m.json")]
    assert main([*fit, str(plain)]) == 0
    want = capsys.readouterr().out.splitlines()[0].split(" -> ")[1].split(", residual")[0]
    # read without the options: refused, naming the option
    assert main([*fit, str(european)]) == 2
    assert "--delimiter ';'" in capsys.readouterr().err
    assert main([*fit, str(european), "--decimal-comma", "--units", "m,rad"]) == 0
    got = capsys.readouterr().out.splitlines()[0].split(" -> ")[1].split(", residual")[0]
    assert got == want and "rank 10 of 15" in got


async def test_http_upload_of_a_european_ballbar_file_with_query_options(client: httpx.AsyncClient) -> None:
    headers = {**auth("engineer"), "Content-Type": "text/csv"}
    text = _european(_ballbar_csv())
    bare = await client.post("/api/datasets", params={"name": "bb"}, content=text, headers=headers)
    assert bare.status_code == 422 and "--delimiter ';'" in bare.json()["message"], bare.text
    params = {"name": "bb", "decimal_comma": "true", "units": "m,rad"}
    up = await client.post("/api/datasets", params=params, content=text, headers=headers)
    assert up.status_code == 201, up.text
    summary = up.json()["summary"]
    assert summary["campaign"] == "ballbar"
    assert summary["read_as"] == "fields by ';', decimal mark ',', lengths in m, angles in rad"
    stored = await client.get(f"/api/datasets/{up.json()['id']}/content", headers=auth("engineer"))
    stored_bb = read_ballbar(stored.text)
    assert np.max(np.abs(stored_bb.bar_mm - read_ballbar(_ballbar_csv()).bar_mm)) < 1e-9  # mm again
    # the same as multipart form fields
    files = {"file": ("bb.csv", text.encode(), "text/csv")}
    form = {"decimal_comma": "true", "units": "m,rad"}
    up = await client.post("/api/datasets", files=files, data=form, headers=auth("engineer"))
    assert up.status_code == 201 and up.json()["summary"]["campaign"] == "ballbar", up.text
    maybe = await client.post(
        "/api/datasets", files=files, data={"decimal_comma": "maybe"}, headers=auth("engineer")
    )
    assert maybe.status_code == 422 and "decimal_comma 'maybe': expected true or false" in maybe.text
    twice = await client.post(
        "/api/datasets", params={"units": "m,rad"}, files=files, data=form, headers=auth("engineer")
    )
    assert twice.status_code == 422 and twice.json()["column"] == "units", twice.text


@pytest.mark.parametrize(
    ("params", "column", "sentence"),
    [
        ({"units": "m"}, "units", "--units 'm': expected a length unit (mm or m) and an angle unit"),
        ({"delimiter": "|"}, "delimiter", "--delimiter '|': expected one of"),
        ({"euler": "zyx"}, "euler", "--euler 'zyx' is ambiguous"),
        ({"delimiter": ",", "decimal_comma": "true"}, "decimal_comma", "--decimal-comma with ','"),
    ],
)
async def test_http_options_are_refused_with_the_command_lines_sentences(
    client: httpx.AsyncClient, params: dict[str, str], column: str, sentence: str
) -> None:
    headers = {**auth("engineer"), "Content-Type": "text/csv"}
    r = await client.post("/api/datasets", params=params, content=_ballbar_csv(), headers=headers)
    assert r.status_code == 422, r.text
    assert r.json()["column"] == column and sentence in r.json()["message"], r.json()
    files = {"file": ("bb.csv", _ballbar_csv().encode(), "text/csv")}
    r = await client.post("/api/datasets", files=files, data=params, headers=auth("engineer"))
    assert r.status_code == 422 and r.json()["column"] == column and sentence in r.json()["message"]
    op = {**auth("operator"), "Idempotency-Key": "k-" + column, "Content-Type": "text/csv"}
    r = await client.post(
        "/api/batches/file", params=params, content="pose_id,a1,a2,a3,a4,a5,a6\n", headers=op
    )
    assert r.status_code == 422, r.text


async def test_http_target_file_in_radians_with_decimal_commas(client: httpx.AsyncClient) -> None:
    values = [math.radians(AXES[f"a{k}"]) for k in range(1, 7)]
    row = ";".join(["p1", *(repr(v).replace(".", ",") for v in values)])
    text = "pose_id;a1;a2;a3;a4;a5;a6\n" + row + "\n"
    op = {**auth("operator"), "Idempotency-Key": "eu-1", "Content-Type": "text/csv"}
    bare = await client.post("/api/batches/file", content=text, headers=op)
    assert bare.status_code == 422 and "--delimiter ';'" in bare.json()["message"], bare.text
    params = {"decimal_comma": "1", "units": "mm,rad"}
    r = await client.post("/api/batches/file", params=params, content=text, headers=op)
    assert r.status_code == 201, r.text
    request = r.json()["targets"][0]["request"]
    assert [request[f"a{k}"] for k in range(1, 7)] == pytest.approx([AXES[f"a{k}"] for k in range(1, 7)])
