"""The declared tracker uncertainty through every door: CLI, the service's job and request schema.

A campaign without repeated poses has no measured noise floor: without a declaration the diagnosis
claims none (null, and the words say so); with ``--tracker-sigma-mm`` / ``tracker_sigma_mm`` it uses
``√3·σ`` and says ``declared``. The report shows the remainder's structure table.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from diagnosis_campaigns import make_campaign
from pydantic import ValidationError

from comp_daemon.cli import main
from comp_daemon.data.dataset import write_dataset
from comp_daemon.data.table import dataset_to_csv
from comp_daemon.diagnosis import DiagnoseOptions, diagnose
from comp_daemon.diagnosis.report import render_report_html
from comp_daemon.preparation.options import DiagnosisSettings
from comp_daemon.service import job_kinds
from comp_daemon.service.schemas import DiagnosisIn


@pytest.fixture(scope="module")
def campaign():
    return make_campaign("irb120", 91, [], n_poses=90, repeat_fraction=0.0)


def test_cli_without_evidence_claims_no_floor_and_declared_sigma_gives_one(
    tmp_path: Path, campaign, capsys
) -> None:
    data = tmp_path / "c.csv"
    write_dataset(campaign.dataset, data)
    out = tmp_path / "d.json"
    assert main(["diagnose", str(data), "--robot", "irb120", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["noise_floor_mm"] is None and doc["noise_floor_source"] is None
    assert "no noise floor" in capsys.readouterr().out
    assert {r["against"] for r in doc["residual_structure"]} >= {"pose_order", "a1", "payload_kg"}
    rc = main(["diagnose", str(data), "--robot", "irb120", "--json", str(out), "--tracker-sigma-mm", "0.01"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["noise_floor_source"] == "declared"
    assert doc["noise_floor_mm"] == pytest.approx(math.sqrt(3.0) * 0.01)
    rc = main(["diagnose", str(data), "--robot", "irb120", "--json", str(out), "--effects", "ratio,drift"])
    assert rc == 0
    assert json.loads(out.read_text())["method"]["effects_tried"] == ["ratio", "drift"]


def test_report_says_the_remainder_could_not_be_compared_and_lists_the_structure(campaign) -> None:
    diag = diagnose(campaign.dataset, campaign.robot)
    page = render_report_html(diag)
    assert "could not be compared with noise" in page
    assert "Structure in the remainder" in page and ">pose_order<" in page


def test_service_job_passes_the_declared_sigma() -> None:
    camp = make_campaign("kr210", 92, [], n_poses=70, repeat_fraction=0.0)
    args = job_kinds.diagnosis_job_args(
        dataset_to_csv(camp.dataset), "kr210", 7, DiagnosisSettings(tracker_sigma_mm=0.004)
    )
    result = job_kinds.run_diagnosis(*args, progress=lambda *a, **k: None)
    assert result["report"]["noise_floor_source"] == "declared"
    assert result["report"]["noise_floor_mm"] == pytest.approx(math.sqrt(3.0) * 0.004)
    assert "declared" in result["html"]


def test_diagnosis_request_validates_the_sigma() -> None:
    assert DiagnosisIn(dataset_id=1).tracker_sigma_mm is None
    assert DiagnosisIn(dataset_id=1, tracker_sigma_mm=0.005).tracker_sigma_mm == 0.005
    for bad in (0.0, -0.01, float("nan"), float("inf")):
        with pytest.raises(ValidationError):
            DiagnosisIn(dataset_id=1, tracker_sigma_mm=bad)
    with pytest.raises(ValueError, match="tracker_sigma_mm"):
        DiagnoseOptions(tracker_sigma_mm=0.0)
    with pytest.raises(ValueError, match="unknown effect"):
        DiagnoseOptions(effects=("friction",))
