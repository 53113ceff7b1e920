"""Prometheus metrics of the daemon, in one registry served on ``/metrics``.

The objects are module-level so that the daemon's telemetry, the service and the job pool update
them directly (an ``observe`` or ``inc`` costs a few microseconds, no I/O). Resolve labelled children
once (``ENCODER_FAULTS.labels(joint="1", kind="crc")``) and keep them; :func:`encoder_fault_counter`
does that with a cache. This module is the one place that names the metrics.

Names follow Prometheus' conventions (https://prometheus.io/docs/practices/naming/): the prefix
``comp_daemon_``, base units with the unit as suffix (``_seconds``; angles in ``_radians``, the SI
unit, although the daemon works in degrees: multiply by 180/π to show degrees), ``_total`` on
counters, ``_info`` on the build information, no units in labels. Joint labels are ``"1"``..``"6"``
(A1..A6). The registry also carries the standard ``process_*`` metrics of the daemon's process.
:func:`metric_names` lists every exposed series name (deploy/grafana-dashboard.json uses only those).

Encoder fault kinds: ``crc`` (bad CRC6), ``error_bit`` (nE low), ``warning_bit`` (nW low),
``timeout`` (no reply in time), ``gone`` (device vanished), ``garbled`` (unreadable reply).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import cache
from typing import Any

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from comp_daemon import __version__

__all__ = [
    "BUILD_INFO",
    "CONTENT_TYPE_LATEST",
    "ENCODER_FAULTS",
    "ENCODER_FAULT_KINDS",
    "ENCODER_STALE",
    "GRATING_READING_AGE",
    "HTTP_ERRORS",
    "JOBS_FINISHED",
    "JOINT_CORRECTION_RAD",
    "JOINT_ERROR_RAD",
    "LOOP_CYCLE_JITTER",
    "LOOP_REPLY_LATENCY",
    "LOOP_RUNNING",
    "QUEUE_DEPTH",
    "REGISTRY",
    "RSI_LATE_REPLIES",
    "RSI_REJECTED",
    "RSI_SESSIONS",
    "RSI_STOPS",
    "RSI_STOP_CAUSES",
    "RSI_TELEGRAMS",
    "TARGETS_FINISHED",
    "encoder_fault_counter",
    "metric_names",
    "radians",
    "render",
    "set_queue_depth_source",
]

REGISTRY = CollectorRegistry(auto_describe=True)
ProcessCollector(registry=REGISTRY)  # process_cpu_seconds_total, process_resident_memory_bytes, …

BUILD_INFO = Info("comp_daemon_build", "The daemon's version", registry=REGISTRY)
BUILD_INFO.info({"version": __version__})

# reply latency: from datagram received to reply sent; buckets resolve the 0.05–2 ms range finely
LOOP_REPLY_LATENCY = Histogram(
    "comp_daemon_loop_reply_latency_seconds",
    "Time from receiving an RSI telegram to sending its reply",
    buckets=(50e-6, 100e-6, 200e-6, 300e-6, 500e-6, 750e-6, 1e-3, 2e-3, 4e-3, 8e-3, 12e-3, 24e-3),
    registry=REGISTRY,
)
LOOP_CYCLE_JITTER = Histogram(
    "comp_daemon_loop_cycle_jitter_seconds",
    "Absolute deviation of the telegram interval from the configured cycle",
    buckets=(100e-6, 250e-6, 500e-6, 1e-3, 2e-3, 4e-3, 8e-3, 16e-3),
    registry=REGISTRY,
)
RSI_TELEGRAMS = Counter("comp_daemon_rsi_telegrams_total", "RSI telegrams answered", registry=REGISTRY)
RSI_LATE_REPLIES = Counter(
    "comp_daemon_rsi_late_replies_total",
    "Telegrams not answered within the cycle: replies sent after the cycle deadline plus telegrams "
    "never answered because a newer one was queued (the same count as late_replies in /api/status)",
    registry=REGISTRY,
)
RSI_REJECTED = Counter(
    "comp_daemon_rsi_rejected_total",
    "Datagrams refused, by reason (garbled, foreign_address, stale_copy: an older copy of a telegram "
    "already answered, other_sender: a second sender on the controller's address)",
    ["reason"],
    registry=REGISTRY,
)
LOOP_RUNNING = Gauge(
    "comp_daemon_loop_running", "1 while the RSI loop exchanges telegrams", registry=REGISTRY
)
RSI_STOP_CAUSES: tuple[str, ...] = ("late_replies", "timeout", "fault", "operator")
RSI_STOPS = Counter(
    "comp_daemon_rsi_stops_total",
    "RSI sessions that ended, by cause (late_replies, timeout, fault, operator)",
    ["cause"],
    registry=REGISTRY,
)
for _cause in RSI_STOP_CAUSES:
    RSI_STOPS.labels(cause=_cause)  # every cause exposed from the start, at 0
RSI_SESSIONS = Counter(
    "comp_daemon_rsi_sessions_total",
    "RSI sessions the controller started (the first and every restart after a stop)",
    registry=REGISTRY,
)

ENCODER_FAULT_KINDS: tuple[str, ...] = ("crc", "error_bit", "warning_bit", "timeout", "gone", "garbled")
ENCODER_FAULTS = Counter(
    "comp_daemon_encoder_faults_total",
    "Grating readings refused, by joint and kind",
    ["joint", "kind"],
    registry=REGISTRY,
)
ENCODER_STALE = Gauge(
    "comp_daemon_encoder_stale",
    "1 while the joint's grating reading is older than allowed",
    ["joint"],
    registry=REGISTRY,
)
GRATING_READING_AGE = Gauge(
    "comp_daemon_grating_reading_age_seconds",
    "Age of the joint's latest valid grating reading",
    ["joint"],
    registry=REGISTRY,
)
JOINT_ERROR_RAD = Gauge(
    "comp_daemon_joint_error_radians",
    "Grating angle minus target angle, per joint",
    ["joint"],
    registry=REGISTRY,
)
JOINT_CORRECTION_RAD = Gauge(
    "comp_daemon_joint_correction_radians",
    "Total RSI correction applied, per joint",
    ["joint"],
    registry=REGISTRY,
)

QUEUE_DEPTH = Gauge("comp_daemon_target_queue_depth", "Targets waiting in the queue", registry=REGISTRY)
TARGETS_FINISHED = Counter(
    "comp_daemon_targets_finished_total",
    "Targets that reached a final state, by state",
    ["state"],
    registry=REGISTRY,
)
JOBS_FINISHED = Counter(
    "comp_daemon_jobs_finished_total",
    "Jobs that finished, by kind and state",
    ["kind", "state"],
    registry=REGISTRY,
)
HTTP_ERRORS = Counter(
    "comp_daemon_http_internal_errors_total",
    "Requests that ended in an internal error (500)",
    registry=REGISTRY,
)


@cache
def encoder_fault_counter(joint: int, kind: str) -> Any:
    """The counter child for one joint and fault kind (cached: cheap to call in the loop)."""
    if kind not in ENCODER_FAULT_KINDS:
        raise ValueError(f"unknown encoder fault kind {kind!r}")
    return ENCODER_FAULTS.labels(joint=str(joint), kind=kind)


def set_queue_depth_source(source: Callable[[], float] | None) -> None:
    """Make the queue-depth gauge read ``source()`` at scrape time (the store's queue depth)."""
    if source is None:
        QUEUE_DEPTH.set_function(lambda: 0.0)
    else:
        QUEUE_DEPTH.set_function(source)


def radians(deg: float) -> float:
    """Degrees (the daemon's unit) to radians (the metrics' unit)."""
    return deg * (math.pi / 180.0)


_SERIES_SUFFIXES: dict[str, tuple[str, ...]] = {
    "counter": ("_total",),
    "gauge": ("",),
    "histogram": ("_bucket", "_sum", "_count"),
    "info": ("_info",),
}


def metric_names() -> frozenset[str]:
    """Every series name ``/metrics`` can expose (``_total``, ``_bucket``/``_sum``/``_count``, ``_info``…),
    labelled metrics included before their first child exists."""
    names: set[str] = set()
    for family in REGISTRY.collect():
        names.update(family.name + suffix for suffix in _SERIES_SUFFIXES.get(family.type, ("",)))
        names.update(sample.name for sample in family.samples)
    return frozenset(names)


def render() -> bytes:
    """The registry in the Prometheus text format (blocking: call it in a worker thread)."""
    return generate_latest(REGISTRY)
