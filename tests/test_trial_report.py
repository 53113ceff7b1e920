"""The trial's HTML report draws each of its figures (matplotlib, inline SVG), from the stored trial
result the docs show (``docs/trial-result.json``, a full trial's output)."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest

from comp_daemon.trial.report import render_html
from comp_daemon.trial.report_data import table_rows
from comp_daemon.trial.report_html import _html_cards, _html_gratings, _html_run, _html_verdict
from comp_daemon.trial.result import TrialResult

STORED = Path(__file__).resolve().parents[1] / "docs" / "trial-result.json"
POINT_ERRORS = ["point-errors-x", "point-errors-y", "point-errors-z", "point-errors-3d"]
PLOTS = ["error-histogram", "error-histogram-per-method", *POINT_ERRORS, "iso9283"]


@pytest.fixture(scope="module")
def result() -> TrialResult:
    return TrialResult.load(STORED)


def test_report_has_every_figure_with_data(result: TrialResult) -> None:
    page = render_html(result)
    figures = dict(re.findall(r'<figure class=plot id="plot-([^"]+)">(.*?)</figure>', page, re.S))
    assert sorted(figures) == sorted(PLOTS)
    for name, body in figures.items():
        assert body.count("<svg") == 1 and "<figcaption>" in body and "no data" not in body, name
    assert re.findall(r"https?://[^\"' ]*", page) == ["http://www.w3.org/2000/svg"] * page.count("<svg")
    assert "<script" not in page and "data:" not in page
    ids = re.findall(r'\bid="([^"]+)"', page)
    assert len(ids) == len(set(ids))
    # every method run is in every figure: the frequency chart and the per-point plots too, not
    # only seed 000's three
    assert len(table_rows(result)) == len(result.runs) == 5
    for k in table_rows(result):
        assert result.runs[k].label in figures["error-histogram-per-method"]
        assert result.runs[k].label in figures["error-histogram"]
        assert all(result.runs[k].label in figures[p] for p in POINT_ERRORS)
    for name, plot in zip(("x", "y", "z", "3-D"), POINT_ERRORS, strict=True):
        assert f"error {name} per target point" in figures[plot]
    n_points = len(result.iso["points_mm"])
    assert all(f">P{i + 1}<" in figures["iso9283"] for i in range(n_points))
    assert render_html(result) == page


def test_report_of_a_trial_without_iso_or_runs_says_no_data(result: TrialResult) -> None:
    result = TrialResult(plan=result.plan, started_at=result.started_at, environment={})
    page = render_html(result)
    assert page.count("no data:") >= 7
    assert "ISO 9283 test did not run" in page


def test_a_model_without_an_order_shows_a_dash_not_none(result: TrialResult) -> None:
    page = render_html(result)
    assert "None" not in re.sub(r"<svg.*?</svg>", "", page, flags=re.S)
    orders = [m.get("order") for m in result.models.values()]
    assert None in orders and 3 in orders  # the stored trial has both kinds
    assert "<td>3</td>" in page and "<td>–</td>" in page


def test_report_sections_stand_alone(result: TrialResult) -> None:
    grat = _html_gratings(result)
    assert grat.count("<tr><td>A") == len(result.gratings["joints"]) == 3
    assert _html_gratings(TrialResult(plan=result.plan, started_at="", environment={})) == ""
    cards = _html_cards(result)
    assert cards.count("<div class=card>") == 3 and "seed 000: 0.76" in cards
    verdict = {"ordering": {"mean": True, "max": False}, "claim": {"trial": dict.fromkeys(
        ("before_max", "after_max", "reduction", "vs_kinematic", "axis_max_abs"), 0.5)}}  # fmt: skip
    assert "<b>does not hold</b>" in _html_verdict(verdict) and "class=bad" in _html_verdict(verdict)
    assert _html_verdict({}) == ""


def test_run_section_lists_unfinished_and_retried_targets(result: TrialResult) -> None:
    quiet = _html_run(result)
    assert "did not finish" not in quiet and "posted again" not in quiet
    assert quiet.count("<tr><td>") == len(result.phases)
    run = copy.deepcopy(result)
    k = next(iter(run.runs))
    run.runs[k].state[4] = "failed"
    run.runs[k].reason[4] = "a grating went silent"
    run.runs[k].retried.append({"index": 2, "reason": "RSI telegrams late"})
    page = _html_run(run)
    assert f"<li>{run.runs[k].label}, point 5: failed — a grating went silent</li>" in page
    assert f"<li>{run.runs[k].label}, point 3: RSI telegrams late</li>" in page
