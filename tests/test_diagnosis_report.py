"""The HTML report (self-contained, matplotlib figures inline) and ``comp-daemon diagnose`` end to end."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import pytest
from diagnosis_campaigns import NOISE_FLOOR_MM, make_campaign

from comp_daemon.cli import main
from comp_daemon.data.dataset import write_dataset
from comp_daemon.diagnosis import diagnose
from comp_daemon.diagnosis.report import render_report_html

VOID = ("meta", "br")


class _Tags(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.stack: list[str] = []
        self.counts: dict[str, int] = {}
        self.urls: list[str] = []
        self.ids: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.counts[tag] = self.counts.get(tag, 0) + 1
        for name, value in attrs:
            internal = value is not None and (value.startswith(("#", "url(#", "data:image/png;base64,")))
            if (name in ("src", "href") or (value and "url(" in value)) and not internal:
                self.urls.append(f"{name}={value}")
            if name == "id":
                self.ids.append(str(value))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag: str) -> None:
        if tag in VOID:
            return
        assert self.stack and self.stack[-1] == tag, (
            f"</{tag}> closes <{self.stack[-1] if self.stack else None}>"
        )
        self.stack.pop()


RESIDUAL_PLOTS = ["residual-pose", "residual-joint", "variogram", "remainder-time", "predicted-measured"]


@pytest.fixture(scope="module")
def campaign():
    return make_campaign(
        "kr210", 71, [("backlash", 2, 8 * NOISE_FLOOR_MM), ("thermal", None, 5 * NOISE_FLOOR_MM)], n_poses=160
    )


def test_report_is_self_contained_and_draws_every_section(campaign) -> None:
    diag = diagnose(campaign.dataset, campaign.robot)
    page = render_report_html(diag)
    tags = _Tags()
    tags.feed(page)
    tags.close()
    assert tags.stack == []
    assert tags.urls == []
    assert "<script" not in page and "@import" not in page
    assert re.findall(r"https?://[^\"' ]*", page) == ["http://www.w3.org/2000/svg"] * page.count("<svg")
    assert len(tags.ids) == len(set(tags.ids)), "ids repeat across the figures"
    # one figure per plot, each an inline SVG with a caption
    effect_plots = [f"effect-step-{k}" for k in range(2, len(diag.steps) + 1)]
    names = ["ladder", *effect_plots, "joint-error", "check-histogram", *RESIDUAL_PLOTS]
    figures = re.findall(r'<figure class=plot id="plot-([^"]+)">(.*?)</figure>', page, re.S)
    assert [n for n, _ in figures] == names
    for name, body in figures:
        assert body.count("<svg") == 1 and "<figcaption>" in body and "no data" not in body, name
    by_name = dict(figures)
    for j in range(1, 7):
        assert f"residual vs A{j}" in by_name["residual-joint"]
        assert f"Joint {j}: equivalent error vs A{j}" in by_name["joint-error"]
    assert "joint-space distance (deg)" in by_name["variogram"]
    assert "measured = predicted" in by_name["predicted-measured"]
    assert render_report_html(diag) == page  # the same diagnosis gives the same bytes
    for step in diag.steps:
        assert f">{step.effect}<" in page
    assert "backlash contribution" in page and "thermal contribution" in page
    assert "temp_c (°C)" in page
    assert diag.where["summary"][:60].replace("'", "&#x27;") in page


def test_fitted_values_and_rounds_are_tables_and_the_page_prints(campaign) -> None:
    diag = diagnose(campaign.dataset, campaign.robot)
    page = render_report_html(diag)
    text = re.sub(r"<svg.*?</svg>", "", page, flags=re.S)
    assert '{"' not in text and "<code>{" not in text  # no raw JSON left
    values = re.findall(r"<h3 id=values-(\d+)>.*?</h3><table class=values>(.*?)</table>", page, re.S)
    assert [int(k) for k, _ in values] == list(range(1, len(diag.steps) + 1))
    header = "<th class=l>parameter</th><th class=l>meaning</th><th class=l>joint / axis</th>"
    assert all(header in body and "<th>σ</th>" in body for _, body in values)
    backlash = next(body for k, body in values if diag.steps[int(k) - 1].effect == "backlash")
    assert "<code>h2</code>" in backlash and "<td class=l>joint 2</td><td class=l>deg</td>" in backlash
    sigmas = [
        float(v)
        for v in re.findall(r"<td>(-?[\d.e+-]+)</td><td>([\d.e+-]+)</td><td>[\d.]+</td>", backlash)[0]
    ]
    assert sigmas[1] > 0 and abs(sigmas[0]) / sigmas[1] > 3  # the backlash put in is well determined
    geometric = values[0][1]
    assert "link length a" in geometric and "base frame rotation" in geometric
    rounds = re.search(r"<table class=rounds>(.*?)</table>", page, re.S)
    assert rounds is not None and rounds.group(1).count("<tr>") > len(diag.selection)
    accepted = [r["accepted"] for r in diag.selection if r.get("accepted")]
    assert all(f"accepted {a}" in rounds.group(1) for a in accepted)
    assert "@media print" in page and "@page" in page and "break-inside:avoid" in page


def test_the_ladders_log_axis_reads_as_plain_numbers(campaign) -> None:
    page = render_report_html(diagnose(campaign.dataset, campaign.robot))
    ladder = re.search(r'<figure class=plot id="plot-ladder">(.*?)</figure>', page, re.S)
    assert ladder is not None
    ticks = re.findall(r">(\d+(?:\.\d+)?)</text>", ladder.group(1))
    assert {"0.1", "0.2", "0.5"} & set(ticks), ticks
    assert "×" not in ladder.group(1) and "10^" not in ladder.group(1) and "−1" not in ladder.group(1)


def test_cli_writes_json_and_report(tmp_path: Path, campaign, capsys) -> None:
    data = tmp_path / "campaign.csv"
    write_dataset(campaign.dataset, data)
    out, report = tmp_path / "diag.json", tmp_path / "diag.html"
    rc = main(["diagnose", str(data), "--robot", "kr210", "--json", str(out), "--report", str(report)])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert sorted(doc["unmodelled"]) == ["backlash", "thermal"]
    assert doc["where"]["joints"] == [2]
    assert report.read_text().startswith("<!DOCTYPE html>")
    printed = capsys.readouterr().out
    assert "unmodelled: backlash, thermal" in printed


def test_cli_prints_json_without_an_output_file(tmp_path: Path, capsys) -> None:
    camp = make_campaign("irb120", 72, [], n_poses=80)
    data = tmp_path / "c.csv"
    write_dataset(camp.dataset, data)
    assert main(["diagnose", str(data), "--robot", "irb120", "--frame", "base"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["robot"] == "ABB IRB 120" and doc["unmodelled"] == []


def test_cli_refuses_bad_data_and_writes_nothing(tmp_path: Path, capsys) -> None:
    camp = make_campaign("kr210", 73, [], n_poses=60)
    data = tmp_path / "bad.csv"
    write_dataset(camp.dataset, data)
    lines = data.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[5].split(",")
    cells[header.index("a2")] = "20"  # outside A2's limits [-140, -5]
    lines[5] = ",".join(cells)
    data.write_text("\n".join(lines) + "\n")
    out, report = tmp_path / "o.json", tmp_path / "o.html"
    rc = main(["diagnose", str(data), "--robot", "kr210", "--json", str(out), "--report", str(report)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "row 6" in err and "'a2'" in err
    assert not out.exists() and not report.exists()
    assert list(tmp_path.iterdir()) == [data]
