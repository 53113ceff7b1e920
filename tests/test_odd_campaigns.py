"""Campaigns shaped unlike the simulator's defaults, through the doors: few rows, only the required
columns, rows out of visiting order, a robot without link masses. Each door refuses a model the
rows cannot determine by name, or degrades with a sentence; none crashes."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.commands.diagnose import untested_effects
from comp_daemon.data.dataset import DatasetError, read_dataset
from comp_daemon.estimation.registration import scale_problem
from comp_daemon.estimation.selection import selection_line
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects.base import EffectData
from comp_daemon.models.effects.catalogue import COMPLIANCE
from comp_daemon.models.registry import parse_model_name, undetermined_reason
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.preparation.campaign import prepare_directions
from comp_daemon.robot.description import load_robot

REQUIRED = ("a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z")


def _subset(src: Path, dst: Path, columns: tuple[str, ...] | None, rows: int | None = None) -> Path:
    with src.open(newline="") as f:
        table = list(csv.DictReader(f))
    keep = list(columns) if columns is not None else list(table[0])
    with dst.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keep)
        for r in table[:rows]:
            w.writerow([r[c] for c in keep])
    return dst


@pytest.fixture(scope="module")
def kr_campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("odd") / "kr.csv"
    assert main(["sim", "sample", "--n", "30", "--seed", "3", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def mh6_campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("odd") / "mh6.csv"
    assert (
        main(["sim", "sample", "--scenario", "mh6-cell", "--n", "50", "--seed", "6", "--out", str(out)]) == 0
    )
    return out


@pytest.fixture(scope="module")
def repeats_required(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 poses measured twice each, only the required columns."""
    folder = tmp_path_factory.mktemp("odd")
    full = folder / "rep.csv"
    assert main(["sim", "sample", "--n", "30", "--repeats", "2", "--seed", "5", "--out", str(full)]) == 0
    return _subset(full, folder / "req.csv", REQUIRED)


def test_evaluate_all_on_few_rows_leaves_out_the_undetermined_models_by_name(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _subset(kr_campaign, tmp_path / "twelve.csv", REQUIRED, rows=12)
    out = tmp_path / "e.json"
    assert main(["evaluate", str(data), "--robot", "kr210", "--models", "all", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    # only the nominal model (raw, and registered: 6 + 3 parameters) has as few parameters as 12 rows;
    # every other one is named with its reason
    assert sorted(doc["ranking"]) == ["nominal", "nominal, base+tool registered"]
    assert "left out chebyshev: the chebyshev model has 150 parameters; 12 rows leave it undetermined" in text
    assert "kinematic" in doc["skipped"] and "39 parameters" in doc["skipped"]["kinematic"]
    assert doc["split"]["drawn"] and doc["split"]["check_rows"] > 0


def test_evaluate_refuses_when_no_model_is_determined(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _subset(kr_campaign, tmp_path / "twenty.csv", REQUIRED, rows=20)
    assert main(["evaluate", str(data), "--robot", "kr210", "--models", "chebyshev,poe"]) == 2
    err = capsys.readouterr().err
    assert "no model can be evaluated" in err
    assert "chebyshev: the chebyshev model has 150 parameters" in err and "poe: the poe model" in err


def test_fit_names_the_model_the_rows_cannot_determine(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _subset(kr_campaign, tmp_path / "twenty.csv", REQUIRED, rows=20)
    code = main(
        ["fit", str(data), "--robot", "kr210", "--model", "kinematic", "--out", str(tmp_path / "m.json")]
    )
    assert code == 2
    assert "the kinematic model has 39 parameters; 20 rows leave it undetermined" in capsys.readouterr().err
    assert not (tmp_path / "m.json").exists()


def test_compliance_without_link_masses_is_refused_by_name(
    mh6_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "c.json"
    code = main(
        ["fit", str(mh6_campaign), "--robot", "motoman_mh6", "--model", "compliance", "--out", str(out)]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "needs link masses in the robot description" in err and "payload_kg > 0" in err
    assert not out.exists()
    # the same campaign on the preset with masses fits
    assert main(["fit", str(mh6_campaign), "--robot", "mh6", "--model", "compliance", "--out", str(out)]) == 0


def test_evaluate_leaves_out_compliance_on_a_massless_robot(
    mh6_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "e.json"
    models = "nominal,kinematic+compliance,compliance:paper"
    assert (
        main(
            ["evaluate", str(mh6_campaign), "--robot", "motoman_mh6", "--models", models, "--json", str(out)]
        )
        == 0
    )
    doc = json.loads(out.read_text())
    assert sorted(doc["ranking"]) == ["nominal", "nominal, base+tool registered"]
    assert set(doc["skipped"]) == {"kinematic+compliance", "compliance:paper"}
    assert all("link masses" in reason for reason in doc["skipped"].values())
    assert (
        "left out kinematic+compliance: the kinematic+compliance model needs link masses"
        in capsys.readouterr().out
    )


def test_undetermined_reason_takes_a_payload_as_load() -> None:
    massless = load_robot("motoman_mh6")
    spec = parse_model_name("compliance")
    assert undetermined_reason(spec, massless, 100, 0.0) is not None
    assert undetermined_reason(spec, massless, 100, [0.0, 5.0]) is None
    assert undetermined_reason(parse_model_name("kinematic"), massless, 100, 0.0) is None
    assert undetermined_reason(spec, load_robot("kr210"), 100, 0.0) is None


def test_inferred_directions_say_the_row_order_is_assumed(kr_campaign: Path, tmp_path: Path) -> None:
    data = read_dataset(_subset(kr_campaign, tmp_path / "req.csv", REQUIRED))
    note = prepare_directions(data)[1].note
    assert note is not None and "in row order" in note
    assert "assumed: the file lists the poses in the order the robot visited them" in note
    # with a clock the order is the clock's, and nothing is assumed about the file's row order
    timed = read_dataset(_subset(kr_campaign, tmp_path / "timed.csv", (*REQUIRED, "t_s")))
    note = prepare_directions(timed)[1].note
    assert note is not None and "in t_s" in note and "assumed: the file lists" not in note


def test_diagnose_on_few_rows_says_how_many_it_needs(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _subset(kr_campaign, tmp_path / "req.csv", REQUIRED)
    assert main(["diagnose", str(data), "--robot", "kr210"]) == 2
    err = capsys.readouterr().err
    assert "21 fit rows, fewer than the 39 parameters of the geometric step" in err
    assert "give at least 56 rows" in err


def test_a_dropped_part_with_a_lower_held_out_rms_says_why() -> None:
    decision = {"part": "kriging", "kept": False, "rms_without_mm": 0.2268, "rms_with_mm": 0.2251}
    worse = {"part": "ratio", "kept": False, "rms_without_mm": 0.2, "rms_with_mm": 0.21}
    line = selection_line(
        {"selection": {"kept": [], "dropped": ["kriging", "ratio"], "decisions": [decision, worse]}}
    )
    assert line is not None
    assert (
        "kriging (0.2268 mm held out without, 0.2251 with: a gain within 2 standard errors, not kept)" in line
    )
    assert "ratio (0.2000 mm held out without, 0.2100 with)" in line


def test_diagnose_without_dir_infers_the_directions_and_says_the_remainder_is_not_noise(
    repeats_required: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = repeats_required
    assert main(["diagnose", str(data), "--robot", "kr210", "--json", str(tmp_path / "d.json")]) == 0
    out, err = capsys.readouterr()
    doc = json.loads((tmp_path / "d.json").read_text())
    assert "no split column; held out" in err and doc["split"]["drawn"]
    assert doc["noise_floor_source"] == "repeats"
    ratio = doc["unexplained_rms_mm"] / doc["noise_floor_mm"]
    # the simulated cell has backlash the file cannot show: far above the floor, and said so
    assert ratio > 2.0
    assert f"({ratio:.1f} x the floor: not noise" in out
    assert "thermal (no temp_c column" in out and "not tested: backlash" not in out
    assert "unmodelled: none;" not in out
    # backlash is tested on directions inferred from the row order, and the diagnosis says so
    assert doc["directions"]["source"] == "inferred" and doc["directions"]["assumed_row_order"]
    assert "approach directions (dir1..dir6) inferred" in err and "assumed: the file lists" in err
    assert not any(s["effect"] == "backlash" for s in doc["skipped"])


def test_diagnose_finds_backlash_on_directions_inferred_from_the_row_order(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    full = tmp_path / "bl.csv"
    assert (
        main(
            ["sim", "sample", "--scenario", "kr210-backlash", "--n", "120", "--seed", "3", "--out", str(full)]
        )
        == 0
    )
    data = _subset(full, tmp_path / "req.csv", (*REQUIRED, "split"))
    assert main(["diagnose", str(data), "--robot", "kr210", "--json", str(tmp_path / "d.json")]) == 0
    out, err = capsys.readouterr()
    doc = json.loads((tmp_path / "d.json").read_text())
    assert "backlash" in doc["unmodelled"]
    assert doc["directions"]["source"] == "inferred" and doc["directions"]["order"] == "row order"
    assert "assumed: the file lists the poses in the order the robot visited them" in err
    assert "backlash named on approach directions inferred from the row order (assumed" in out


def test_diagnose_no_infer_dir_leaves_backlash_untested_by_name(
    repeats_required: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["diagnose", str(repeats_required), "--robot", "kr210", "--no-infer-dir"]
    assert main([*args, "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    assert "not tested: backlash (no dir1..dir6 columns" in out
    assert json.loads((tmp_path / "d.json").read_text())["directions"] == {"source": "none"}


def _scaled(src: Path, dst: Path, factor: float, rows: int) -> Path:
    with src.open(newline="") as f:
        table = list(csv.DictReader(f))[:rows]
    with dst.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(REQUIRED)
        for r in table:
            w.writerow([r[c] if c.startswith("a") else repr(float(r[c]) * factor) for c in REQUIRED])
    return dst


def test_positions_in_metres_are_refused_not_fitted_to_zero(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _scaled(kr_campaign, tmp_path / "metres.csv", 1e-3, rows=30)
    out = tmp_path / "m.json"
    # a kinematic calibration could shrink every length a thousand times and fit "perfectly"
    assert main(["fit", str(data), "--robot", "kr210", "--model", "nominal", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "spread 0.001 times as far as the nominal TCP positions" in err and "(in metres?)" in err
    assert not out.exists()
    assert main(["diagnose", str(data), "--robot", "kr210"]) == 2
    assert "not millimetres of this robot (in metres?)" in capsys.readouterr().err


def test_data_check_refuses_metres_by_the_rule_fit_and_diagnose_apply(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``data check`` used to say ``ok: true`` on a campaign in metres that fit and diagnose refuse."""
    mm = _scaled(kr_campaign, tmp_path / "mm.csv", 1.0, rows=30)
    assert main(["data", "check", str(mm), "--robot", "kr210"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"] is True
    for name, factor, unit in (("metres", 1e-3, "metres"), ("inches", 1 / 25.4, "inches")):
        data = _scaled(kr_campaign, tmp_path / f"{name}.csv", factor, rows=30)
        assert main(["data", "check", str(data), "--robot", "kr210"]) == 2
        captured = capsys.readouterr()
        refusal = json.loads(captured.out)
        assert refusal["ok"] is False and refusal["column"] == "x, y, z"
        assert f"not millimetres of this robot (in {unit}?)" in refusal["error"]
        sentence = refusal["error"].split(": ", 1)[1]
        fit = ["fit", str(data), "--robot", "kr210", "--model", "nominal", "--out", str(tmp_path / "m")]
        assert main(fit) == 2
        assert sentence in capsys.readouterr().err
        assert main(["diagnose", str(data), "--robot", "kr210"]) == 2
        assert sentence in capsys.readouterr().err


def test_scale_problem_passes_a_rigidly_moved_campaign_and_names_inches() -> None:
    rng = np.random.default_rng(1)
    p = rng.normal(size=(40, 3)) * 400.0
    angle = np.radians(37.0)
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    far = p @ rot.T + np.array([4200.0, -3100.0, 850.0])
    assert scale_problem(p, far + rng.normal(scale=0.05, size=p.shape)) is None
    assert "(in inches?)" in str(scale_problem(p, far / 25.4))
    # too little spread to judge: no claim either way
    assert scale_problem(p * 0.01, p * 0.00001) is None


def test_diagnose_says_a_declared_sigma_is_not_used_when_repeats_measure_the_noise(
    repeats_required: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = repeats_required
    args = [
        "diagnose",
        str(data),
        "--robot",
        "kr210",
        "--tracker-sigma-mm",
        "0.01",
        "--json",
        str(tmp_path / "d.json"),
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "noise floor" in out and "(repeats)" in out
    assert "--tracker-sigma-mm not used: the repeats measure the noise" in out


def test_untested_effects_count_every_joint_of_an_effect() -> None:
    skipped: list[dict[str, Any]] = [
        {"effect": "backlash", "joints": [1, 2, 3, 4, 5], "reason": "no dir1..dir6 columns"},
        {"effect": "backlash", "joints": [6], "reason": "joint 6 does not move the TCP"},
        {"effect": "compliance", "joints": [1], "reason": "no gravity torque on joint 1"},
        {"effect": "thermal", "joints": [], "reason": "no temp_c column"},
    ]
    assert untested_effects(skipped) == (
        "backlash (no dir1..dir6 columns / joint 6 does not move the TCP); thermal (no temp_c column)"
    )


def test_a_drift_on_the_row_order_says_the_row_order_is_the_clock(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    full = tmp_path / "full.csv"
    assert main(["sim", "sample", "--n", "90", "--seed", "4", "--out", str(full)]) == 0
    with full.open(newline="") as f:
        table = list(csv.DictReader(f))
    columns = [*REQUIRED, "dir1", "dir2", "dir3", "dir4", "dir5", "dir6"]
    data = tmp_path / "drift.csv"
    with data.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for i, r in enumerate(table):  # a tracker drifting 0.6 mm along x over the campaign, no t_s
            r["x"] = repr(float(r["x"]) + 0.6 * i / len(table))
            w.writerow([r[c] for c in columns])
    assert main(["diagnose", str(data), "--robot", "kr210", "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "d.json").read_text())
    assert "drift" in doc["unmodelled"] and doc["clock"]["from"] == "pose_order"
    assert "clock: the row order (no t_s column): drift" in out


@pytest.mark.parametrize(("sep", "what"), [(";", "semicolons"), ("\t", "tabs")])
def test_a_file_separated_by_semicolons_or_tabs_is_named_as_such(
    kr_campaign: Path, tmp_path: Path, sep: str, what: str
) -> None:
    text = _subset(kr_campaign, tmp_path / "req.csv", REQUIRED).read_text().replace(",", sep)
    with pytest.raises(DatasetError, match=f"the header is one column holding {what}; this format separates"):
        read_dataset(text.encode())


def test_an_unseen_reflector_says_how_to_leave_it_out(kr_campaign: Path, tmp_path: Path) -> None:
    lines = _subset(kr_campaign, tmp_path / "req.csv", REQUIRED).read_text().splitlines()
    header = lines[0] + ",x2,y2,z2"
    body = [line + ",1.0,2.0,3.0" for line in lines[1:]]
    body[3] = lines[4] + ",,,"
    with pytest.raises(DatasetError, match=r"row 5, column 'x2': empty cell.*leave out that pose's row"):
        read_dataset("\n".join([header, *body]).encode())


def test_compliance_on_a_massless_robot_is_skipped_for_the_masses_not_a_vertical_axis() -> None:
    n = 20
    rows = MeasuredRows(np.zeros((n, 6)), np.zeros((n, 3)))
    data = EffectData(rows, np.zeros((n, 6)), np.ones(6, dtype=bool))
    for joint in (1, 2, 3):
        reason = COMPLIANCE.data_reason(data, joint)
        assert reason is not None and "the robot description has no link masses" in reason
    tau = np.zeros((n, 6))
    tau[:, 1] = np.linspace(10.0, 200.0, n)  # joint 2 loaded, joint 1 vertical
    loaded = EffectData(rows, tau, np.ones(6, dtype=bool))
    assert "its axis is vertical" in str(COMPLIANCE.data_reason(loaded, 1))
    assert COMPLIANCE.data_reason(loaded, 2) is None


def test_frame_base_on_tracker_frame_data_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "tracker.csv"
    assert main(["sim", "sample", "--n", "50", "--seed", "8", "--tracker-frame", "--out", str(data)]) == 0
    out = tmp_path / "m.json"
    args = ["fit", str(data), "--robot", "kr210", "--model", "nominal", "--frame", "base", "--out", str(out)]
    assert main(args) == 0
    assert "--frame base, but the measured positions lie" in capsys.readouterr().out
    assert "frame_warning" in json.loads(out.read_text())["fit"]
    # auto registers the frame and has nothing to warn about
    assert main(["fit", str(data), "--robot", "kr210", "--model", "nominal", "--out", str(out)]) == 0
    assert "--frame base" not in capsys.readouterr().out


def test_a_drawn_split_of_repeated_poses_says_it_keeps_them_together(tmp_path: Path) -> None:
    full = tmp_path / "rep.csv"
    assert main(["sim", "sample", "--n", "20", "--repeats", "3", "--seed", "5", "--out", str(full)]) == 0
    ds = read_dataset(_subset(full, tmp_path / "req.csv", REQUIRED))
    split = ds.split_or_draw()
    assert ds.a_deg is not None
    assert "60 rows are 20 poses by identical axis values; a pose's repeats stay together" in split.message
    check_poses = {tuple(a) for a in ds.a_deg[split.check_rows]}
    assert not check_poses & {tuple(a) for a in ds.a_deg[split.fit_rows]}
    single = read_dataset(_subset(full, tmp_path / "one.csv", REQUIRED, rows=1)).split_or_draw()
    assert "repeats stay together" not in single.message


def _one_pose(src: Path, dst: Path, n: int, move_a1: bool = False) -> Path:
    """``n`` rows of the first pose of ``src`` (repeats), or with only A1 stepping when ``move_a1``
    (positions: the nominal KR210's)."""
    with src.open(newline="") as f:
        first = next(csv.DictReader(f))
    a = np.tile([float(first[f"a{k}"]) for k in range(1, 7)], (n, 1))
    xyz = np.tile([float(first[c]) for c in "xyz"], (n, 1))
    if move_a1:
        a[:, 0] += 0.5 * np.arange(n)
        nominal = KinematicParams.from_robot(load_robot("kr210"))
        xyz = tcp_position_mm(nominal, axes_deg_to_q_rad(a, nominal.sign))
    xyz[:, 0] += 0.01 * (np.arange(n) % 3)
    with dst.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(REQUIRED)
        for i in range(n):
            w.writerow([repr(float(v)) for v in (*a[i], *xyz[i])])
    return dst


def test_one_pose_repeated_is_refused_by_every_door_with_the_reason(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _one_pose(kr_campaign, tmp_path / "same.csv", 45)
    out = tmp_path / "m.json"
    assert main(["fit", str(data), "--robot", "kr210", "--model", "kinematic", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert "A1, A2, A3, A4, A5, A6 do not move on the fit rows" in captured.out
    assert "the fit rows hold 1 distinct pose(s)" in captured.err and not out.exists()
    assert main(["evaluate", str(data), "--robot", "kr210", "--models", "nominal,kinematic"]) == 2
    assert "one pose (repeats): none left to hold out" in capsys.readouterr().err
    assert main(["diagnose", str(data), "--robot", "kr210"]) == 2
    assert "the 45 rows are one pose" in capsys.readouterr().err


def test_a_campaign_moving_one_axis_says_the_others_stand_still(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _one_pose(kr_campaign, tmp_path / "a1.csv", 45, move_a1=True)
    out = tmp_path / "m.json"
    assert main(["fit", str(data), "--robot", "kr210", "--model", "nominal", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "A2, A3, A4, A5, A6 do not move on the fit rows" in text and "elsewhere it extrapolates" in text


def test_an_unreachable_target_is_named_by_its_row(
    kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = tmp_path / "m.json"
    assert main(["fit", str(kr_campaign), "--robot", "kr210", "--model", "nominal", "--out", str(model)]) == 0
    targets = tmp_path / "t.csv"
    targets.write_text("tx,ty,tz\n1800,0,800\n9000,0,800\n1900,50,900\n")
    assert main(["compensate", str(model), str(targets), "--out", str(tmp_path / "c.csv")]) == 3
    err = capsys.readouterr().err
    assert "refused row 3: unreachable within joint limits (left" in err and "target 2" not in err


def test_compliance_on_a_massless_robot_with_payloads_fits_and_says_what_it_sees(
    mh6_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with mh6_campaign.open(newline="") as f:
        table = list(csv.DictReader(f))
    data = tmp_path / "loaded.csv"
    with data.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([*REQUIRED, "payload_kg"])
        for i, r in enumerate(table):
            w.writerow([*(r[c] for c in REQUIRED), "0" if i % 2 else "5"])
    out = tmp_path / "c.json"
    assert main(["fit", str(data), "--robot", "motoman_mh6", "--model", "compliance", "--out", str(out)]) == 0
    assert "has no link masses: the compliance sees the payload's torque only" in capsys.readouterr().out


def test_diagnose_frame_base_on_tracker_frame_data_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    full = tmp_path / "tracker.csv"
    assert main(["sim", "sample", "--n", "60", "--seed", "8", "--tracker-frame", "--out", str(full)]) == 0
    data = _subset(full, tmp_path / "req.csv", REQUIRED)
    args = ["diagnose", str(data), "--robot", "kr210", "--frame", "base", "--json", str(tmp_path / "d.json")]
    assert main(args) == 0
    assert "--frame base, but the nominal twin misses the measurements by" in capsys.readouterr().out


@pytest.mark.parametrize(("value", "meant"), [("train", "fit"), ("test", "check"), ("Validation", "check")])
def test_a_split_named_as_other_tools_name_it_gets_a_hint(kr_campaign: Path, value: str, meant: str) -> None:
    text = kr_campaign.read_text().replace(",fit,", f",{value},").replace(",check,", f",{value},")
    with pytest.raises(DatasetError, match=f"got '{value}'; did you mean '{meant}'"):
        read_dataset(text.encode())


@pytest.mark.parametrize("folds", ["0", "1", "21", "x"])
def test_fold_counts_that_cannot_cross_validate_are_refused(
    kr_campaign: Path, folds: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main(["evaluate", str(kr_campaign), "--robot", "kr210", "--models", "nominal", "--folds", folds])
    assert "expected 2..20 folds" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (",fit,", ",check,", "0 fit rows, fewer than the 3 poses a fit needs (the split column marks 0"),
        (",check,", ",fit,", "no check rows to judge on (the split marks no row 'check')"),
    ],
    ids=["no-fit-rows", "no-check-rows"],
)
def test_a_split_column_without_fit_or_check_rows_is_refused_by_name(
    old: str, new: str, message: str, kr_campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "one-sided.csv"
    data.write_text(kr_campaign.read_text().replace(old, new))
    assert main(["evaluate", str(data), "--robot", "kr210", "--models", "nominal"]) == 2
    assert message in capsys.readouterr().err


def test_compensating_with_a_backlash_model_without_dir_infers_or_says_it_is_not_applied(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "c.csv"
    assert main(["sim", "sample", "--n", "70", "--seed", "9", "--out", str(data)]) == 0
    model = tmp_path / "m.json"
    args = ["fit", str(data), "--robot", "kr210", "--model", "kinematic:all+backlash", "--out", str(model)]
    assert main(args) == 0
    # a nominal program (a1..a6) takes its directions from its row order, as the fit did, and says so
    targets = _subset(data, tmp_path / "t.csv", ("a1", "a2", "a3", "a4", "a5", "a6"), rows=5)
    capsys.readouterr()
    assert main(["compensate", str(model), str(targets), "--out", str(tmp_path / "o.csv")]) == 0
    out = capsys.readouterr().out
    assert "approach directions (dir1..dir6) inferred" in out and "assumed: the file lists" in out
    assert "backlash is not applied" not in out
    # TCP targets have no axis values to order: the backlash cannot be applied, and that is said
    tcp = tmp_path / "tcp.csv"
    tcp.write_text("tx,ty,tz\n1800,0,800\n1900,50,900\n")
    assert main(["compensate", str(model), str(tcp), "--out", str(tmp_path / "o.csv")]) == 0
    assert "no dir1..dir6 columns: the model's backlash is not applied" in capsys.readouterr().out
    with_dir = _subset(
        data,
        tmp_path / "td.csv",
        (*(f"a{k}" for k in range(1, 7)), *(f"dir{k}" for k in range(1, 7))),
        rows=5,
    )
    assert main(["compensate", str(model), str(with_dir), "--out", str(tmp_path / "o.csv")]) == 0
    assert "backlash is not applied" not in capsys.readouterr().out


def _no_progress(*_: Any, **__: Any) -> None:
    return None


def test_the_http_fit_job_names_the_model_the_rows_cannot_determine(
    kr_campaign: Path, mh6_campaign: Path, tmp_path: Path
) -> None:
    from comp_daemon.service.job_kinds import run_fit

    few = _subset(kr_campaign, tmp_path / "few.csv", None, rows=20).read_text()
    with pytest.raises(
        ValueError, match="the chebyshev model has 150 parameters; 20 rows leave it undetermined"
    ):
        run_fit(few, "kr210", "chebyshev", None, 7, progress=_no_progress)
    massless = mh6_campaign.read_text()
    with pytest.raises(ValueError, match="needs link masses in the robot description"):
        run_fit(massless, "motoman_mh6", "compliance", None, 8, progress=_no_progress)
    done = run_fit(few, "kr210", "nominal", None, 7, progress=_no_progress)
    assert (
        done["stats"]["kind"] == "nominal"
        and done["stats"]["rows"]["fit"] + done["stats"]["rows"]["check"] == 20
    )


def test_diagnose_with_an_empty_effects_list_is_refused(
    kr_campaign: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as refused:
        main(["diagnose", str(kr_campaign), "--robot", "kr210", "--effects", " , "])
    assert refused.value.code == 2
    assert "argument --effects: names no effect" in capsys.readouterr().err
