"""Prometheus metrics of the daemon, in one registry served on ``/metrics``.

The objects are module-level so that the real-time loop updates them directly (an ``observe`` or
``inc`` costs a few microseconds, no I/O). Resolve labelled children once, outside the loop
(``ENCODER_FAULTS.labels(joint="1", kind="crc")``) and keep them; :func:`encoder_fault_counter`
does that with a cache. Units are in the names (``_seconds``, ``_deg``), as Prometheus asks.

Encoder fault kinds: ``crc`` (bad CRC6), ``error_bit`` (nE low), ``warning_bit`` (nW low),
``timeout`` (no reply in time), ``gone`` (device vanished), ``garbled`` (unreadable reply).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

__all__ = [
    "CONTENT_TYPE_LATEST",
    "ENCODER_FAULTS",
    "ENCODER_FAULT_KINDS",
    "ENCODER_STALE",
    "HTTP_ERRORS",
    "JOBS_FINISHED",
    "JOINT_CORRECTION_DEG",
    "JOINT_ERROR_DEG",
    "LOOP_CYCLE_JITTER",
    "LOOP_REPLY_LATENCY",
    "LOOP_RUNNING",
    "QUEUE_DEPTH",
    "REGISTRY",
    "RSI_LATE_REPLIES",
    "RSI_REJECTED",
    "RSI_TELEGRAMS",
    "TARGETS_FINISHED",
    "encoder_fault_counter",
    "render",
    "set_queue_depth_source",
]

REGISTRY = CollectorRegistry(auto_describe=True)

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
RSI_TELEGRAMS = Counter("comp_daemon_rsi_telegrams", "RSI telegrams answered", registry=REGISTRY)
RSI_LATE_REPLIES = Counter(
    "comp_daemon_rsi_late_replies",
    "Replies sent after the cycle deadline or telegrams skipped because a newer one was queued",
    registry=REGISTRY,
)
RSI_REJECTED = Counter(
    "comp_daemon_rsi_rejected",
    "Datagrams refused, by reason (garbled, foreign_address)",
    ["reason"],
    registry=REGISTRY,
)
LOOP_RUNNING = Gauge(
    "comp_daemon_loop_running", "1 while the RSI loop exchanges telegrams", registry=REGISTRY
)

ENCODER_FAULT_KINDS: tuple[str, ...] = ("crc", "error_bit", "warning_bit", "timeout", "gone", "garbled")
ENCODER_FAULTS = Counter(
    "comp_daemon_encoder_faults",
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
JOINT_ERROR_DEG = Gauge(
    "comp_daemon_joint_error_deg", "Grating angle minus target angle, per joint", ["joint"], registry=REGISTRY
)
JOINT_CORRECTION_DEG = Gauge(
    "comp_daemon_joint_correction_deg",
    "Total RSI correction applied, per joint",
    ["joint"],
    registry=REGISTRY,
)

QUEUE_DEPTH = Gauge("comp_daemon_target_queue_depth", "Targets waiting in the queue", registry=REGISTRY)
TARGETS_FINISHED = Counter(
    "comp_daemon_targets_finished",
    "Targets that reached a final state, by state",
    ["state"],
    registry=REGISTRY,
)
JOBS_FINISHED = Counter(
    "comp_daemon_jobs_finished", "Jobs that finished, by kind and state", ["kind", "state"], registry=REGISTRY
)
HTTP_ERRORS = Counter(
    "comp_daemon_http_internal_errors", "Requests that ended in an internal error (500)", registry=REGISTRY
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


def render() -> bytes:
    """The registry in the Prometheus text format (blocking: call it in a worker thread)."""
    return generate_latest(REGISTRY)
