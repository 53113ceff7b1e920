"""deploy/grafana-dashboard.json asks only for metrics the daemon exposes, and covers every part.

Each PromQL expression (panel targets and annotations) is reduced to its metric names: label
matchers, ranges, ``by``/``without``/``on``/``ignoring`` groupings, strings and numbers removed,
function names (followed by ``(``) and keywords dropped. Every name left must be a series of the
daemon's registry, the one ``GET /metrics`` renders; the names follow Prometheus' conventions.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from comp_daemon.service import metrics

DASHBOARD = Path(__file__).resolve().parents[1] / "deploy" / "grafana-dashboard.json"

_KEYWORDS = {
    "by",
    "without",
    "on",
    "ignoring",
    "group_left",
    "group_right",
    "bool",
    "and",
    "or",
    "unless",
    "offset",
    "inf",
    "nan",
}


def expressions(node: Any) -> Iterator[str]:
    """Every ``expr`` in the dashboard (panels, rows' panels, annotations), recursively."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "expr" and isinstance(value, str):
                yield value
            else:
                yield from expressions(value)
    elif isinstance(node, list):
        for item in node:
            yield from expressions(item)


def metric_names_in(expr: str) -> set[str]:
    text = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # strings (label values, regexes)
    text = re.sub(r"\{[^}]*\}", " ", text)  # label matchers
    text = re.sub(r"\[[^\]]*\]", " ", text)  # ranges and subqueries
    text = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", text)
    names = set()
    for m in re.finditer(r"(?<![\w$.])([A-Za-z_:][\w:]*)\s*(\()?", text):
        name, call = m.group(1), m.group(2)
        if call or name.lower() in _KEYWORDS:
            continue
        names.add(name)
    return names


def test_the_parser_finds_metric_names_and_nothing_else() -> None:
    expr = (
        'histogram_quantile(0.99, sum by (le) (rate(comp_daemon_x_bucket{job=~"$job", a="b(c)"}[5m]))) '
        "/ on (instance) group_left ignoring (kind) other_metric offset 5m * 180 / 3.14 > bool 0"
    )
    assert metric_names_in(expr) == {"comp_daemon_x_bucket", "other_metric"}
    assert metric_names_in("time() - process_start_time_seconds") == {"process_start_time_seconds"}


@pytest.fixture(scope="module")
def dashboard() -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    return doc


def test_every_expression_uses_only_metrics_the_daemon_exposes(dashboard: dict[str, Any]) -> None:
    exprs = list(expressions(dashboard))
    assert len(exprs) >= 20
    exposed = metrics.metric_names()
    rendered = metrics.render().decode()
    used: set[str] = set()
    for expr in exprs:
        names = metric_names_in(expr)
        assert names, f"no metric in {expr!r}"
        unknown = names - exposed
        assert not unknown, f"{expr!r} uses {sorted(unknown)}, not exposed on /metrics"
        used |= names
    # what /metrics serves: each used series belongs to a family with its HELP line there
    families = {n for n in re.findall(r"^# HELP (\S+)", rendered, re.M)}
    for name in used:
        base = re.sub(r"_(total|bucket|sum|count|info)$", "", name)
        assert name in families or base in families, name


def test_every_part_of_the_daemon_has_a_panel(dashboard: dict[str, Any]) -> None:
    used = set().union(*(metric_names_in(e) for e in expressions(dashboard)))
    for family in (
        "comp_daemon_loop_reply_latency_seconds_bucket",  # loop: cycle time quantiles
        "comp_daemon_loop_cycle_jitter_seconds_bucket",
        "comp_daemon_rsi_late_replies_total",  # late replies
        "comp_daemon_rsi_stops_total",  # stops by cause
        "comp_daemon_loop_running",
        "comp_daemon_encoder_faults_total",  # gratings
        "comp_daemon_encoder_stale",
        "comp_daemon_grating_reading_age_seconds",
        "comp_daemon_target_queue_depth",  # queue and targets
        "comp_daemon_targets_finished_total",
        "comp_daemon_jobs_finished_total",  # fits and jobs
        "comp_daemon_http_internal_errors_total",  # HTTP
    ):
        assert family in used, family
    titles = [p["title"] for p in dashboard["panels"]]
    assert all(titles) and len(titles) == len(set(titles))
    for p in dashboard["panels"]:
        assert p["type"] == "row" or p["targets"], p["title"]


def test_metric_names_follow_the_prometheus_conventions() -> None:
    names = {n for n in metrics.metric_names() if not n.endswith("_created")}
    for family in metrics.REGISTRY.collect():
        name = family.name
        assert name.startswith(("comp_daemon_", "process_")), name
        if family.type == "counter":
            assert f"{name}_total" in names, name
        if family.type == "info":
            assert f"{name}_info" in names, name
        # base units only: seconds, bytes, radians (no ms, mm, degrees)
        assert not re.search(r"_(ms|milliseconds|mm|millimeters|deg|degrees|percent)(_|$)", name), name
        for sample in family.samples:
            for label in sample.labels:
                assert not re.search(r"_(s|ms|mm|deg|seconds|bytes)$", label), (name, label)
    assert metrics.RSI_STOP_CAUSES == ("late_replies", "timeout", "fault", "operator")
