"""The project's own format docs: their example files are read by the readers they describe, the
diagnosis example is a real diagnosis of the example campaign, links resolve, and nothing a user
reads points outside the repository."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import read_dataset, read_dataset_json
from comp_daemon.robot.description import load_robot

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "docs" / "examples"
KR = load_robot("kr210")

# every column of the campaign table in docs/data-format.md
CAMPAIGN_COLUMNS = (
    *(f"a{k}" for k in range(1, 7)),
    "x", "y", "z", "x2", "y2", "z2",
    *(f"dir{k}" for k in range(1, 7)),
    "g1", "g2", "g3", "payload_kg", "temp_c", "t_s", "split", "repeat", "pose_id",
    "station", "qw", "qx", "qy", "qz", "sigma_mm",
)  # fmt: skip


def test_the_template_has_every_column_and_is_accepted(capsys: pytest.CaptureFixture[str]) -> None:
    template = EXAMPLES / "campaign-template.csv"
    header = template.read_text("utf-8").splitlines()[0].split(",")
    assert sorted(header) == sorted(CAMPAIGN_COLUMNS)
    assert main(["data", "check", str(template), "--robot", "kr210"]) == 0
    assert json.loads(capsys.readouterr().out)["rows"] == 3
    as_json = read_dataset_json(EXAMPLES / "campaign.json", limits_deg=KR.axis_limits_deg)
    as_csv = read_dataset(template, limits_deg=KR.axis_limits_deg)
    for name in ("a_deg", "xyz_mm", "reflectors_mm", "dir", "g_deg", "payload_kg", "temp_c", "t_s"):
        np.testing.assert_array_equal(getattr(as_json, name), getattr(as_csv, name), err_msg=name)
    assert list(as_json.split) == list(as_csv.split) and list(as_json.pose_id) == list(as_csv.pose_id)


@pytest.mark.parametrize(
    ("name", "kind"),
    [("campaign.csv", "measurement"), ("targets-axes.csv", "targets"), ("targets-tcp.csv", "targets")],
)
def test_example_files_pass_data_check(name: str, kind: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "check", str(EXAMPLES / name), "--robot", "kr210", "--kind", kind]) == 0
    assert json.loads(capsys.readouterr().out)["ok"] is True


def test_the_example_robot_file_is_the_preset() -> None:
    assert load_robot(EXAMPLES / "kr210.toml").to_dict() == KR.to_dict()


def test_the_diagnosis_example_is_the_example_campaigns_with_the_documented_fields() -> None:
    doc = json.loads((EXAMPLES / "diagnosis.json").read_text("utf-8"))
    campaign = read_dataset(EXAMPLES / "campaign.csv", limits_deg=KR.axis_limits_deg)
    assert doc["data"]["content_sha256"] == campaign.content_sha256
    assert doc["robot"] == KR.name and doc["robot_sha256"] == KR.sha256
    assert doc["rows"]["fit"] + doc["rows"]["check"] == len(campaign)
    assert doc["baseline"]["effect"] == "nominal"
    step_fields = {"effect", "joints", "significant", "check_rms_mm", "check_max_mm", "shrink_pct", "params"}
    assert all(step_fields <= set(step) for step in doc["steps"])
    significant = [s["effect"] for s in doc["steps"] if s["significant"] and s["effect"] != "geometric"]
    assert doc["unmodelled"] == significant
    assert doc["noise_floor_source"] in ("repeats", "targets", "declared", None)
    assert {"against", "share_pct", "significant"} <= set(doc["residual_structure"][0])


def _user_files() -> list[Path]:
    files = [REPO / "README.md", REPO / "config.example.toml", *sorted((REPO / "docs").glob("*.md"))]
    for pattern in ("*.py", "*.toml"):
        files += sorted((REPO / "comp_daemon").rglob(pattern))
    return files


def test_nothing_a_user_reads_points_outside_the_repository() -> None:
    outside = re.compile(r"shared/spec|\.\./shared|\bspec/(dataset|diagnose|seeds-002-003|rsi|encoder-link)")
    hits = [
        f"{path.relative_to(REPO)}:{k}"
        for path in _user_files()
        for k, line in enumerate(path.read_text("utf-8").splitlines(), start=1)
        if outside.search(line)
    ]
    assert hits == []


def test_relative_links_of_the_docs_resolve() -> None:
    link = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
    broken = []
    for page in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for target in link.findall(page.read_text("utf-8")):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(REPO)} -> {target}")
    assert broken == []
