"""The diagnosis beside the compensation models fitted on the same rows (``model_comparison``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from diagnosis_campaigns import NOISE_FLOOR_MM, make_campaign

from comp_daemon.cli import main
from comp_daemon.data.dataset import write_dataset
from comp_daemon.diagnosis import DiagnoseOptions, diagnose
from comp_daemon.diagnosis.comparison import AGREE_PCT
from comp_daemon.models.fitting import FitOptions
from comp_daemon.models.registry import fit_spec, parse_model_name
from comp_daemon.preparation.campaign import PrepareOptions, prepare_campaign
from comp_daemon.preparation.options import COMPARED_MODELS

#: backlash of joints 2 and 3, eight times the noise floor each
BACKLASH_2_3: list[tuple[str, int | None, float]] = [
    ("backlash", 2, 8 * NOISE_FLOOR_MM),
    ("backlash", 3, 8 * NOISE_FLOOR_MM),
]


def test_unknown_model_names_are_refused() -> None:
    with pytest.raises(ValueError, match="krigin"):
        DiagnoseOptions(compare_models=("kinematic", "krigin"))
    assert DiagnoseOptions(compare_models=("kriging:aniso",)).compare_models == ("kriging:aniso",)


def test_a_model_with_what_the_ladder_was_not_given_is_named() -> None:
    """Backlash on two joints, the ladder's vocabulary without backlash: kinematic+ratio+backlash
    does clearly better on the same check rows, and the diagnosis says so and why."""
    camp = make_campaign(
        "kr210", 21, [("backlash", 2, 8 * NOISE_FLOOR_MM), ("backlash", 3, 8 * NOISE_FLOOR_MM)]
    )
    options = DiagnoseOptions(effects=("ratio", "cyclic", "compliance"))
    doc = diagnose(camp.dataset, camp.robot, options).to_json()
    cmp = doc["model_comparison"]
    assert [m["model"] for m in cmp["models"]] == sorted(
        COMPARED_MODELS, key=lambda n: next(m["check_rms_mm"] for m in cmp["models"] if m["model"] == n)
    )
    assert cmp["ladder_check_rms_mm"] == doc["unexplained_rms_mm"]
    assert cmp["best"] == "kinematic+ratio+backlash"
    assert cmp["better_pct"] > AGREE_PCT and cmp["agree"] is False
    assert "backlash" in cmp["lacks"] and "on every joint at once" in cmp["lacks"]
    assert "kinematic+ratio+backlash explains" in cmp["summary"]


def test_the_ladder_with_the_whole_vocabulary_agrees_and_the_figures_are_the_registry_s() -> None:
    """The same campaign with the whole vocabulary: the ladder names the backlash and is within the
    limit of every model; the models' figures are those of fitting them through the registry on the
    diagnosis's fit rows and judging them on its check rows."""
    camp = make_campaign(
        "kr210", 21, [("backlash", 2, 8 * NOISE_FLOOR_MM), ("backlash", 3, 8 * NOISE_FLOOR_MM)]
    )
    options = DiagnoseOptions()
    doc = diagnose(camp.dataset, camp.robot, options).to_json()
    cmp = doc["model_comparison"]
    assert cmp["agree"] is True and cmp["lacks"] is None
    prepared = prepare_campaign(
        camp.dataset, camp.robot, PrepareOptions(need_directions=True, seed=options.seed)
    )
    check = prepared.rows(prepared.check_rows)
    assert cmp["check_rows"] == len(prepared.check_rows) == doc["rows"]["check"]
    for entry in cmp["models"]:
        fitted = fit_spec(
            parse_model_name(entry["model"]),
            camp.robot,
            prepared.rows(prepared.fit_rows),
            FitOptions(frame=prepared.frame, cv_folds=options.folds, seed=options.seed),
        )
        pred = fitted.model.predict_tcp_mm(check.a_deg, check.dir, check.payload_kg, check.temp_c)
        err = np.asarray(camp.dataset.xyz_mm)[prepared.check_rows] - pred
        assert entry["check_rms_mm"] == pytest.approx(np.sqrt(np.mean(np.sum(err**2, axis=1))), rel=1e-5)


def test_the_comparison_can_be_left_out_and_a_model_without_its_data_is_skipped() -> None:
    camp = make_campaign("kr210", 22, [("ratio", 2, 5 * NOISE_FLOOR_MM)], with_dir=False, n_poses=160)
    none = diagnose(camp.dataset, camp.robot, DiagnoseOptions(compare_models=())).to_json()
    assert "model_comparison" not in none
    options = DiagnoseOptions(
        compare_models=("kinematic+ratio+backlash", "kinematic"), infer_directions=False
    )
    cmp = diagnose(camp.dataset, camp.robot, options).to_json()["model_comparison"]
    assert [m["model"] for m in cmp["models"]] == ["kinematic"]
    assert cmp["skipped"][0]["model"] == "kinematic+ratio+backlash"
    assert "dir" in cmp["skipped"][0]["reason"]


def test_the_command_line_and_the_report_say_the_comparison(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    camp = make_campaign("irb120", 92, [("backlash", 2, 8 * NOISE_FLOOR_MM)], n_poses=90, repeat_fraction=0.0)
    data, out, page = tmp_path / "c.csv", tmp_path / "d.json", tmp_path / "d.html"
    write_dataset(camp.dataset, data)
    argv = ["diagnose", str(data), "--robot", "irb120", "--json", str(out), "--report", str(page)]
    assert main([*argv, "--compare-models", "kinematic,kriging"]) == 0
    printed = capsys.readouterr().out
    cmp = json.loads(out.read_text("utf-8"))["model_comparison"]
    assert sorted(m["model"] for m in cmp["models"]) == ["kinematic", "kriging"]
    assert f"models: {cmp['summary']}" in printed
    assert "Beside the compensation models" in page.read_text("utf-8")
    assert main([*argv, "--compare-models", "none"]) == 0
    assert "model_comparison" not in json.loads(out.read_text("utf-8"))
    assert "models: " not in capsys.readouterr().out
