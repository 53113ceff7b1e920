"""Cross-bar campaigns: the form's reader and its refusals, and the simulated campaign → kinematic
model → tracker check rows of the same robot."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.ballbar import ballbar_dataset, read_ballbar
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.crossbar import SOCKETS, read_crossbar
from comp_daemon.data.dataset import dataset_to_csv, read_dataset
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, ballbar_lengths_mm
from comp_daemon.instruments.ballbar_plan import ballbar_plan
from comp_daemon.instruments.campaign_fit import fit_campaign
from comp_daemon.kinematics.params import PARAM_NAMES
from comp_daemon.kinematics.poe import irb120_table1
from comp_daemon.models.artifact import load_model
from comp_daemon.robot.description import load_robot
from comp_daemon.sim.bars import run_crossbar_campaign
from comp_daemon.sim.scenario import load_scenario

ROBOT = load_robot("mh6")
ROBOT_FILE = "motoman_mh6"  # seed 003's MH6 as the spec describes it
SCENARIO = load_scenario("mh6-cell")


@pytest.fixture(scope="module")
def campaign_csv() -> str:
    return dataset_to_csv(run_crossbar_campaign(SCENARIO, placements=18, seed=2, seating_sigma_mm=0.0))


def _rows(text: str) -> tuple[list[str], list[list[str]]]:
    lines = text.splitlines()
    return lines[0].split(","), [line.split(",") for line in lines[1:]]


def _join(header: list[str], rows: list[list[str]]) -> str:
    return "\n".join([",".join(header), *(",".join(r) for r in rows)]) + "\n"


def _set(text: str, row: int, column: str, value: str) -> str:
    header, rows = _rows(text)
    rows[row - 2][header.index(column)] = value
    return _join(header, rows)


def test_reader_groups_sockets_by_placement(campaign_csv: str) -> None:
    campaign = read_crossbar(campaign_csv, limits_deg=ROBOT.axis_limits_deg)
    assert campaign.n_placements == 18 and len(campaign) == 72
    a, lengths = campaign.readings()
    assert a.shape == (18, 4, 6) and np.all(lengths == 400.0)
    # free column order: the sockets of a placement may come in any order
    header, rows = _rows(campaign_csv)
    rows[0], rows[2] = rows[2], rows[0]
    swapped = read_crossbar(_join(header, rows))
    np.testing.assert_array_equal(swapped.readings()[0], a)


@pytest.mark.parametrize(
    ("edit", "row", "column", "message"),
    [
        (lambda t: _set(t, 3, "socket", "A"), 3, "socket", "holds socket A twice"),
        (lambda t: _set(t, 4, "socket", "E"), 4, "socket", "one of A, B, C, D"),
        (lambda t: _set(t, 4, "socket", "c"), 4, "socket", "did you mean 'C'"),
        (lambda t: _set(t, 6, "bar_l_mm", "0"), 6, "bar_l_mm", "must be > 0"),
        (lambda t: _set(t, 7, "bar_l_mm", "401"), 7, "bar_l_mm", "must be the same"),
        (lambda t: _set(t, 8, "placement", "-2"), 8, "placement", "integer >= 1"),
    ],
)
def test_reader_refusals_name_row_and_column(
    campaign_csv: str, edit: object, row: int, column: str, message: str
) -> None:
    with pytest.raises(DatasetError, match=message) as err:
        read_crossbar(edit(campaign_csv))  # type: ignore[operator]
    assert (err.value.row, err.value.column) == (row, column)


def test_reader_refusals_of_missing_sockets_columns_and_too_few_placements(campaign_csv: str) -> None:
    header, rows = _rows(campaign_csv)
    with pytest.raises(DatasetError, match="lacks socket B") as err:
        read_crossbar(_join(header, rows[:1] + rows[2:]))
    assert err.value.column == "socket"
    k = header.index("socket")
    with pytest.raises(DatasetError, match="required column missing") as err:
        read_crossbar(
            _join(
                [h for j, h in enumerate(header) if j != k],
                [[c for j, c in enumerate(r) if j != k] for r in rows],
            )
        )
    assert (err.value.row, err.value.column) == (1, "socket")
    with pytest.raises(DatasetError, match="13 placements"):
        read_crossbar(_join(header, rows[: 13 * 4]))
    assert read_crossbar(_join(header, rows[: 14 * 4])).n_placements == 14
    # repeats of a placement are groups of their own
    again = [[*r] for r in rows[:4]]
    header_r = [*header, "repeat"]
    rows_r = [[*r, "0"] for r in rows] + [[*r, "1"] for r in again]
    assert len(read_crossbar(_join(header_r, rows_r)).group_rows) == 19
    # a split cuts no placement
    header_s = [*header, "split"]
    rows_s = [[*r, "check" if i == 1 else "fit"] for i, r in enumerate(rows)]
    with pytest.raises(DatasetError, match="whole placements") as err:
        read_crossbar(_join(header_s, rows_s))
    assert err.value.column == "split"
    assert SOCKETS == ("A", "B", "C", "D")


def test_campaign_without_seating_error_recovers_the_hidden_geometry(campaign_csv: str) -> None:
    """No seating error: what is left are the plant's backlash and joint repeatability (hundredths
    of a mm), so the well-conditioned parameters come back to a few hundredths of a mm / 0.01°."""
    fitted, _ = fit_campaign(ROBOT, read_crossbar(campaign_csv))
    info = fitted.info
    assert info["rank"] == 21 and {"theta1", "d1"} <= set(info["not_identifiable"])
    assert info["bar_error_max_before_mm"] > 4.0 and info["bar_error_max_after_mm"] < 0.1
    truth = SCENARIO.true_dx()
    for name in ("alpha1", "theta2", "alpha2", "beta2", "d3", "a4", "theta5", "a5"):
        k = PARAM_NAMES.index(name)
        tol = 0.06 if name[0] in "ad" and not name.startswith("alpha") else 2e-4
        assert info["identified"][name]["value"] == pytest.approx(truth[k], abs=tol), name


def test_simulated_campaign_calibrates_for_the_tracker(tmp_path: Path) -> None:
    """The spec's robot file (``motoman_mh6``: probe (40, 0, 100) mm, no masses) through every door:
    the hidden MH6 cell with that description, its cross-bar campaign, fit, evaluate, compensate."""
    cb, trk, model, report = (tmp_path / n for n in ("cb.csv", "trk.csv", "cb.json", "ev.json"))
    sample = ["sim", "sample", "--scenario", "crossbar", "--robot", ROBOT_FILE]
    assert main([*sample, "--n", "18", "--seed", "1", "--out", str(cb)]) == 0
    assert main(["fit", str(cb), "--robot", ROBOT_FILE, "--model", "kinematic", "--out", str(model)]) == 0
    assert load_model(model).model.kind == "kinematic"
    assert (
        main(
            [
                "sim",
                "sample",
                "--scenario",
                "mh6-cell",
                "--robot",
                ROBOT_FILE,
                "--n",
                "60",
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
                ROBOT_FILE,
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
    assert table["cb.json"]["3d"]["rms"] < 0.1 * table["nominal"]["3d"]["rms"]
    out = tmp_path / "c.csv"
    targets = tmp_path / "t.csv"
    targets.write_text("a1,a2,a3,a4,a5,a6\n10,10,-20,5,-60,30\n-15,20,-10,-5,-50,0\n")
    # the MH6 preset errors are millimetres: compensation moves axes by about a degree
    assert (
        main(["compensate", str(model), str(targets), "--out", str(out), "--max-axis-change-deg", "3"]) == 0
    )
    corrected = read_dataset(out, kind="targets")
    assert max(float(v) for v in corrected.extra["predicted_error_mm"]) < 1e-5


def test_ballbar_and_crossbar_fits_give_one_summary(campaign_csv: str) -> None:
    """The entries a campaign fit's ``info`` holds whatever the instrument, each of the same kind."""
    irb120 = load_robot("irb120")
    plan = ballbar_plan(irb120, 3)
    bar = ballbar_lengths_mm(irb120_table1(irb120), plan.a_deg, np.full(15, 0.01), PAPER_PIVOT_MM)
    ballbar, _ = fit_campaign(
        irb120,
        read_ballbar(dataset_to_csv(ballbar_dataset(plan.a_deg, plan.arc, PAPER_PIVOT_MM, bar_mm=bar))),
    )
    crossbar, _ = fit_campaign(ROBOT, read_crossbar(campaign_csv))
    for fitted, rows in ((ballbar, plan.arc.size), (crossbar, 4 * crossbar.info["crosses"])):
        info = fitted.info
        assert info["campaign"] == info["kind"] and info["rows"] == rows
        assert {"method", "iterations", "stop"} <= set(info["solver"])
        assert "near_dependent" in info["identifiability"] and isinstance(info["not_identifiable"], list)
        assert 0 < info["rank"] <= info["parameters"] and info["rms_mm"] >= 0.0
        assert all("value" in v for v in info["identified"].values())
        assert info["frame"].startswith("robot base (nominal)")
    assert set(ballbar.info) & set(crossbar.info) == {
        "kind", "campaign", "rows", "rms_mm", "rank", "parameters", "solver", "identifiability",
        "not_identifiable", "identified", "frame",
    }  # fmt: skip
