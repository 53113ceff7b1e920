"""Ballbar campaigns: the form's reader and its refusals, fit → poe artifact through the CLI and the
HTTP service, and the simulated campaign judged on tracker data of the same robot."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from service_client import in_process_service, job_done
from test_service_api import auth, make_settings

from comp_daemon.cli import main
from comp_daemon.commands.campaigns import nominal_tcp
from comp_daemon.data.ballbar import ballbar_dataset, read_ballbar
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.dataset import dataset_to_csv
from comp_daemon.instruments.ballbar import (
    BALLBAR_PARAM_NAMES,
    PAPER_PIVOT_MM,
    ballbar_lengths_mm,
    to_canonical,
)
from comp_daemon.instruments.ballbar_plan import TABLE5_ERRORS, ballbar_plan
from comp_daemon.kinematics.poe import irb120_table1
from comp_daemon.models.artifact import load_model
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("irb120")
PLAN = ballbar_plan(ROBOT, 3)
TRUTH = np.concatenate([TABLE5_ERRORS, [0.8, -0.6, 0.5]])


def _csv(bar: np.ndarray | None = None, **extra: tuple[str, ...]) -> str:
    lengths = (
        ballbar_lengths_mm(irb120_table1(ROBOT), PLAN.a_deg, TRUTH, PAPER_PIVOT_MM)
        if bar is None
        else bar
    )
    ds = ballbar_dataset(PLAN.a_deg, PLAN.arc, PAPER_PIVOT_MM, bar_mm=lengths, extra=dict(extra))
    return dataset_to_csv(ds)


def _edit(text: str, row: int, column: str, value: str) -> str:
    lines = text.splitlines()
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = value
    lines[row - 1] = ",".join(cells)
    return "\n".join(lines) + "\n"


def _drop(text: str, column: str) -> str:
    lines = [line.split(",") for line in text.splitlines()]
    k = lines[0].index(column)
    return "\n".join(",".join(c for j, c in enumerate(cells) if j != k) for cells in lines) + "\n"


def test_reader_takes_a_good_file_and_keeps_unknown_columns() -> None:
    text = _csv(note=("x",) * len(PLAN.a_deg))
    campaign = read_ballbar(text, tcp_mm=nominal_tcp(ROBOT), limits_deg=ROBOT.axis_limits_deg)
    assert len(campaign) == 103 and sorted(set(campaign.arc.tolist())) == [1, 2, 3]
    np.testing.assert_array_equal(campaign.pivot_mm, PAPER_PIVOT_MM)
    assert campaign.rows.extra["note"][0] == "x"
    # the nominal + reading form gives the same lengths
    bar = campaign.bar_mm
    pair = _drop(_csv(), "bar_mm")
    lines = pair.splitlines()
    lines[0] += ",bar_nominal_mm,dr_um"
    for i in range(1, len(lines)):
        lines[i] += f",100.0,{float((bar[i - 1] - 100.0) * 1000.0)!r}"
    other = read_ballbar("\n".join(lines) + "\n")
    np.testing.assert_allclose(other.bar_mm, bar, atol=1e-9)


@pytest.mark.parametrize(
    ("edit", "row", "column", "message"),
    [
        (lambda t: _drop(t, "bar_mm"), 1, "bar_mm", "required column missing"),
        (lambda t: _drop(t, "cy"), 1, "cy", "required column missing"),
        (lambda t: _drop(t, "arc"), 1, "arc", "required column missing"),
        (lambda t: _drop(t, "a4"), 1, "a4", "column missing"),
        (lambda t: _edit(t, 7, "bar_mm", "-1.0"), 7, "bar_mm", "must be > 0"),
        (lambda t: _edit(t, 9, "bar_mm", "abc"), 9, "bar_mm", "not a number"),
        (lambda t: _edit(t, 12, "cx", "351.0"), 12, "cx", "must be the same"),
        (lambda t: _edit(t, 5, "arc", "0"), 5, "arc", "integer >= 1"),
        (lambda t: _edit(t, 5, "arc", "1.5"), 5, "arc", "integer >= 1"),
        (lambda t: _edit(t, 20, "bar_mm", "108.0"), 20, "bar_mm", "wrong pivot"),
        (lambda t: _edit(t, 3, "a2", "400"), 3, "a2", "outside the axis limits"),
    ],
)
def test_reader_refusals_name_row_and_column(edit: Any, row: int, column: str, message: str) -> None:
    with pytest.raises(DatasetError, match=message) as err:
        read_ballbar(edit(_csv()), tcp_mm=nominal_tcp(ROBOT), limits_deg=ROBOT.axis_limits_deg)
    assert (err.value.row, err.value.column) == (row, column)


def test_reader_refusals_of_the_whole_file() -> None:
    short = "\n".join(_csv().splitlines()[:15]) + "\n"  # 14 rows
    with pytest.raises(DatasetError, match="at least 15"):
        read_ballbar(short)
    split = np.where(PLAN.arc == 1, "check", "fit")
    split[3] = "fit"  # arc 1 cut in two
    ds = ballbar_dataset(
        PLAN.a_deg, PLAN.arc, PAPER_PIVOT_MM, bar_mm=np.full(len(PLAN.arc), 100.0), split=split
    )
    with pytest.raises(DatasetError, match="whole arcs") as err:
        read_ballbar(dataset_to_csv(ds))
    assert err.value.column == "split"
    both = _csv(bar_nominal_mm=("100.0",) * len(PLAN.arc))
    with pytest.raises(DatasetError, match="not both"):
        read_ballbar(both)
    ids = tuple(f"p{i // 2}" for i in range(len(PLAN.arc)))
    ds = ballbar_dataset(
        PLAN.a_deg, PLAN.arc, PAPER_PIVOT_MM, bar_mm=np.full(len(PLAN.arc), 100.0), pose_id=ids
    )
    with pytest.raises(DatasetError, match="at least 2") as err:
        read_ballbar(dataset_to_csv(ds), uncertainty=True)  # 103 rows: the last pose has one
    assert err.value.column == "pose_id"
    with pytest.raises(DatasetError, match="needs pose_id"):
        read_ballbar(_csv(), uncertainty=True)


def test_fit_cli_recovers_the_canonical_truth_and_names_what_it_cannot_see(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "ballbar.csv"
    data.write_text(_csv())
    out = tmp_path / "model.json"
    assert main(["fit", str(data), "--robot", "irb120", "--model", "poe", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rank 10 of 15" in text and "dtheta1" in text and "not identifiable" in text
    model = load_model(out).model
    canonical = to_canonical(TRUTH, PAPER_PIVOT_MM)
    fitted_len = ballbar_lengths_mm(
        irb120_table1(ROBOT),
        PLAN.a_deg,
        np.concatenate([model.x, json.loads(out.read_text())["fit"]["pivot_offset_mm"]]),
        PAPER_PIVOT_MM,
    )  # type: ignore[attr-defined]
    true_len = ballbar_lengths_mm(irb120_table1(ROBOT), PLAN.a_deg, TRUTH, PAPER_PIVOT_MM)
    assert np.abs(fitted_len - true_len).max() < 1e-6
    for name in ("dl3", "dl4", "dtheta2", "dtheta4", "dtheta5"):
        k = BALLBAR_PARAM_NAMES.index(name)
        assert model.x[k] == pytest.approx(canonical[k], abs=1e-6)  # type: ignore[attr-defined]
    assert main(["fit", str(data), "--robot", "irb120", "--model", "chebyshev", "--out", str(out)]) == 2
    assert "calibrates the poe model" in capsys.readouterr().err


def test_simulated_campaign_improves_the_tracker_check_rows(tmp_path: Path) -> None:
    bb, trk, model, report = (tmp_path / n for n in ("bb.csv", "trk.csv", "bb.json", "ev.json"))
    assert main(["sim", "sample", "--scenario", "ballbar", "--n", "3", "--seed", "1", "--out", str(bb)]) == 0
    assert main(["fit", str(bb), "--robot", "irb120", "--model", "poe", "--out", str(model)]) == 0
    assert (
        main(
            [
                "sim",
                "sample",
                "--scenario",
                "irb120-geometric",
                "--n",
                "80",
                "--seed",
                "3",
                "--tracker-frame",
                "--out",
                str(trk),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "evaluate",
                str(trk),
                "--robot",
                "irb120",
                "--models",
                "nominal",
                "--calibrated",
                str(model),
                "--json",
                str(report),
            ]
        )
        == 0
    )
    table = json.loads(report.read_text())["table2"]
    assert table["bb.json"]["3d"]["rms"] < 0.75 * table["nominal"]["3d"]["rms"]


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[httpx.AsyncClient]:
    settings = make_settings(tmp_path, jobs={"workers": 1}, robot={"name": "irb120"})
    async with in_process_service(settings) as (c, _):
        yield c


async def test_http_upload_and_fit_job_of_a_ballbar_campaign(client: httpx.AsyncClient) -> None:
    headers = {**auth("engineer"), "Content-Type": "text/csv"}
    bad = await client.post("/api/datasets?name=bb", content=_edit(_csv(), 6, "cz", "390"), headers=headers)
    assert bad.status_code == 422 and bad.json()["row"] == 6 and bad.json()["column"] == "cz"
    records = [
        dict(zip(_csv().splitlines()[0].split(","), line.split(","), strict=True))
        for line in _csv().splitlines()[1:]
    ]
    for r in records:  # JSON numbers where the form has numbers
        for k in r:
            if k != "pose_id":
                r[k] = float(r[k])
    records[4]["arc"] = 0
    bad = await client.post("/api/datasets?name=bb", json=records, headers=auth("engineer"))
    assert bad.status_code == 422 and bad.json()["row"] == 5 and bad.json()["column"] == "arc", bad.text
    records[4]["arc"] = 1
    ok = await client.post("/api/datasets?name=bbj", json=records, headers=auth("engineer"))
    assert ok.status_code == 201 and ok.json()["summary"]["campaign"] == "ballbar", ok.text
    up = await client.post("/api/datasets?name=bb", content=_csv(), headers=headers)
    assert up.status_code == 201, up.text
    r = await client.post(
        "/api/fits", json={"dataset_id": up.json()["id"], "model": "poe"}, headers=auth("engineer")
    )
    assert r.status_code == 202, r.text
    job = await job_done(client, r.json()["id"])
    assert job["state"] == "done", job["error"]
    stats = job["result"]["stats"]
    assert stats["campaign"] == "ballbar" and stats["kind"] == "poe" and stats["rank"] == 10
    assert any("dtheta1" in line for line in stats["not_identifiable"])
    # the pairs the lengths barely tell apart, by name, correlation and condition
    assert {"dl4", "dtheta3"} in [set(p["pair"]) for p in stats["near_dependent"]]
    assert all(p["condition"] > 19 for p in stats["near_dependent"]) and stats["near_dependent_fixed"] == []


def test_a_split_holds_out_whole_arcs_and_judges_the_fit_on_them() -> None:
    from comp_daemon.data.campaigns import campaign_of
    from comp_daemon.instruments.campaign_fit import fit_campaign
    from comp_daemon.sim.bars import run_ballbar_campaign
    from comp_daemon.sim.scenario import load_scenario

    table = run_ballbar_campaign(load_scenario("irb120-geometric"), arcs=5, check_arcs=1, seed=4)
    campaign = campaign_of(table, tcp_mm=nominal_tcp(ROBOT))
    assert campaign is not None and table.split is not None
    held = {int(k) for k, s in zip(campaign.arc, table.split, strict=True) if s == "check"}
    assert len(held) == 1
    fitted, check = fit_campaign(ROBOT, campaign, model="poe")
    assert held.isdisjoint(fitted.info["arcs"]) and check["check_rows"] == int((table.split == "check").sum())
    before, after = check["bar_error_rms_mm"]["before"], check["bar_error_rms_mm"]["after"]
    assert after < 0.25 * before


async def test_http_fit_job_of_a_repeated_ballbar_campaign_reports_its_uncertainty(
    client: httpx.AsyncClient,
) -> None:
    repeats = 3
    n = len(PLAN.arc)
    rng = np.random.default_rng(5)
    exact = ballbar_lengths_mm(irb120_table1(ROBOT), PLAN.a_deg, TRUTH, PAPER_PIVOT_MM)
    ds = ballbar_dataset(
        np.tile(PLAN.a_deg, (repeats, 1)),
        np.tile(PLAN.arc, repeats),
        PAPER_PIVOT_MM,
        bar_mm=np.tile(exact, repeats) + rng.normal(0.0, 0.002, repeats * n),
        pose_id=tuple(f"p{i}" for i in np.tile(np.arange(n), repeats)),
        repeat=np.repeat(np.arange(repeats), n),
    )
    headers = {**auth("engineer"), "Content-Type": "text/csv"}
    up = await client.post("/api/datasets?name=bbr", content=dataset_to_csv(ds), headers=headers)
    assert up.status_code == 201, up.text
    r = await client.post(
        "/api/fits", json={"dataset_id": up.json()["id"], "model": "poe"}, headers=auth("engineer")
    )
    job = await job_done(client, r.json()["id"])
    assert job["state"] == "done", job["error"]
    unc = job["result"]["stats"]["uncertainty"]
    assert unc["poses"] == n and unc["repeats"] == {"min": repeats, "max": repeats}
    assert 0.5e-3 < unc["u_mm"]["mean"] < 4e-3
    assert unc["b_mm"]["mean"] == pytest.approx(1.96 * unc["u_mm"]["mean"])
    assert unc["nested_rounds"] >= 1 and "weighted" in unc["rms_mm"]
