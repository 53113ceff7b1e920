"""One fit pipeline: ``comp-daemon fit`` and the HTTP fit job refuse with the same sentence and fit
the same model; the row floor is MIN_POSES, at the least."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_service_api import campaign_csv

from comp_daemon.cli import main
from comp_daemon.data.dataset import parse_dataset
from comp_daemon.models.registry import MIN_POSES, parse_model_name
from comp_daemon.preparation.campaign import CampaignError, PrepareOptions
from comp_daemon.preparation.options import FitSettings
from comp_daemon.preparation.pipeline import FitRequest, fit_dataset
from comp_daemon.robot.description import load_robot
from comp_daemon.service.job_kinds import run_fit

KR = load_robot("kr210")


def _quiet(*args: Any, **kwargs: Any) -> None:
    return None


def _one_pose(n: int) -> str:
    lines = campaign_csv(n).splitlines()
    first = lines[1].split(",")
    return (
        "\n".join([lines[0], *(",".join([*first[:-1], "fit" if i % 4 else "check"]) for i in range(n))])
        + "\n"
    )


@pytest.mark.parametrize(
    ("text", "model", "cli_extra", "words"),
    [
        (campaign_csv(20), "kinematic", [], "the kinematic model has 39 parameters; 20 rows"),
        (_one_pose(60), "kinematic", [], "the fit rows hold 1 distinct pose(s)"),
        (campaign_csv(60), "kriging-backlash", ["--no-infer-dir"], "needs the dir1..dir6 column(s)"),
    ],
    ids=["too-few-rows", "one-pose", "no-directions"],
)
def test_the_command_line_and_the_job_refuse_in_the_same_words(
    text: str,
    model: str,
    cli_extra: list[str],
    words: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    data = tmp_path / "campaign.csv"
    data.write_text(text)
    out = tmp_path / "model.json"
    argv = ["fit", str(data), "--robot", "kr210", "--model", model, *cli_extra, "--out", str(out)]
    assert main(argv) == 2 and not out.exists()
    said = capsys.readouterr().err.strip().splitlines()[-1]
    prefix = "comp-daemon fit: error: "
    assert said.startswith(prefix) and words in said
    with pytest.raises(ValueError) as refused:
        settings = FitSettings(infer_dir="--no-infer-dir" not in cli_extra)
        run_fit(text, "kr210", model, None, 5, settings, progress=_quiet)
    assert str(refused.value) == said.removeprefix(prefix).replace(str(data), "dataset 5")


def test_the_command_line_and_the_job_fit_the_same_model(tmp_path: Path) -> None:
    text = campaign_csv(80)  # with a split column: both fit on its fit rows
    data = tmp_path / "campaign.csv"
    data.write_text(text)
    out = tmp_path / "model.json"
    assert main(["fit", str(data), "--robot", "kr210", "--model", "kinematic", "--out", str(out)]) == 0
    cli = json.loads(out.read_text())
    job = run_fit(text, "kr210", "kinematic", None, 5, progress=_quiet)["artifact"]
    assert cli["data_sha256"] == job["data_sha256"]
    assert cli["model"] == json.loads(json.dumps(job["model"]))
    assert cli["fit"]["data_rows_used"] == job["fit"]["data_rows_used"] == "fit rows"


def test_the_pipeline_fits_the_fit_rows_and_keeps_what_the_artifact_needs() -> None:
    ds = parse_dataset(campaign_csv(80), source="c")
    outcome = fit_dataset(ds, KR, FitRequest(parse_model_name("kinematic"), hold_out=False))
    assert len(outcome.fit_rows) == 60 and outcome.info["data_source"] == "c"
    doc = outcome.artifact()
    assert doc["data_sha256"] == ds.content_sha256 and doc["fit"]["model"] == "kinematic"
    assert np.isfinite(outcome.info["rms_mm"])


def test_the_row_floor_is_min_poses_at_the_least() -> None:
    assert PrepareOptions().min_fit_rows == MIN_POSES
    with pytest.raises(ValueError, match=f"min_fit_rows must be at least MIN_POSES \\({MIN_POSES}\\)"):
        PrepareOptions(min_fit_rows=MIN_POSES - 1)
    lines = campaign_csv(8).splitlines()  # 2 fit rows, 6 check rows
    marked = [
        lines[0],
        *(line.rsplit(",", 1)[0] + (",fit" if i < 2 else ",check") for i, line in enumerate(lines[1:])),
    ]
    ds = parse_dataset("\n".join(marked) + "\n", source="c")
    with pytest.raises(CampaignError, match="2 fit rows, fewer than the 3 poses a fit needs"):
        fit_dataset(ds, KR, FitRequest(parse_model_name("nominal")))
