"""The daemon's telemetry: loop statistics, Prometheus metrics and the dashboard's live events.

Every ``telemetry_s`` the daemon's supervisor calls :meth:`Telemetry.update`. It computes the loop
statistics from the RSI counters and latency rings that the real-time process reports (percentiles
in a worker thread, over a copy of the rings), adds what is new since the last update to the
metrics (:mod:`comp_daemon.service.metrics`: every reply's latency and every cycle's jitter into
their histograms, late replies, rejected telegrams, grating faults and reading ages, per-joint
errors and corrections in radians), and publishes the
``loop`` and ``joints`` events on the bus the dashboard's event stream reads.

**Late replies** are counted once, here: :attr:`Telemetry.late_replies` is the number of telegrams
the daemon did not answer within the cycle since it started, i.e. replies sent later than
``late_after_ms`` (the cycle) plus telegrams never answered because a newer one was already queued
(the controller counts both as late). It adds up across restarts of the real-time process. The same
figure is ``late_replies`` in :class:`LoopStats` (``/api/status`` → ``daemon.loop``, the dashboard,
the ``loop`` event) and ``comp_daemon_rsi_late_replies_total`` in ``/metrics``. The controller's own
count (``Delay``) restarts with each RSI session and also counts replies delayed on the network; it is
kept per stop in the RSI report.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from dataclasses import asdict
from typing import Any

import numpy as np

from comp_daemon.daemon.rt_process import ReaderMirror
from comp_daemon.rt.loop import LoopView
from comp_daemon.rt.rsi_server import RsiServerStats
from comp_daemon.service import metrics
from comp_daemon.service.daemon_view import LoopStats
from comp_daemon.service.events import EventBus

__all__ = ["Telemetry"]

_ENCODER_METRIC_KIND = {
    "crc": "crc",
    "error_bit": "error_bit",
    "silent": "timeout",
    "gone": "gone",
    "garbled": "garbled",
}


def _percentiles(lat: np.ndarray, jit: np.ndarray) -> tuple[float | None, float | None, float | None]:
    """Latency p50 and p99 and |jitter| p99, in ms (None without samples)."""
    p50 = p99 = j99 = None
    if lat.size:
        p50, p99 = (float(v) / 1e6 for v in np.percentile(lat, [50.0, 99.0]))
    if jit.size:
        j99 = float(np.percentile(np.abs(jit), 99.0)) / 1e6
    return p50, p99, j99


class Telemetry:
    """Loop statistics, metrics and events; see the module docstring."""

    def __init__(self, bus: EventBus, cycle_ms: float) -> None:
        self.bus = bus
        self.cycle_ms = cycle_ms
        self.loop_stats = LoopStats(running=False)
        self.late_replies = 0  # see the module docstring: the one late-reply count
        self._marks: dict[str, int] = {}

    async def update(
        self,
        runtime: LoopView,
        stats: RsiServerStats,
        readers: Mapping[int, ReaderMirror],
        *,
        realtime: str,
        state: str,
    ) -> LoopStats:
        """New loop statistics (also kept as :attr:`loop_stats`), metrics and events."""
        lat = stats.latency.recent()  # copies: the reports append to the rings
        jit = stats.jitter.recent()
        p50, p99, j99 = await asyncio.to_thread(_percentiles, lat, jit)
        late = self._delta("late", stats.late) + self._delta("superseded", stats.superseded)
        if late:
            self.late_replies += late
            metrics.RSI_LATE_REPLIES.inc(late)
        self.loop_stats = LoopStats(
            running=runtime.rsi_alive(),
            cycle_ms=self.cycle_ms,
            cycles=stats.answered,
            late_replies=self.late_replies,
            rejected=stats.foreign + stats.garbled,
            latency_p50_ms=p50,
            latency_p99_ms=p99,
            latency_max_ms=None if stats.latency.max is None else stats.latency.max / 1e6,
            jitter_p99_ms=j99,
            last_ipoc=runtime.last_ipoc,
            realtime=realtime,
        )
        rows = runtime.joint_rows()
        self._update_metrics(runtime, stats, lat, jit, readers, rows)
        self.bus.publish("loop", asdict(self.loop_stats) | {"state": state})
        self.bus.publish("joints", {"joints": rows, "state": str(runtime.core.state)})
        return self.loop_stats

    def _delta(self, key: str, value: int) -> int:
        """What ``value`` (a counter of the real-time process) grew by since the last update; a value
        below the last one is a new real-time process counting from zero: all of it is new."""
        before = self._marks.get(key, 0)
        self._marks[key] = value
        return value - before if value >= before else value

    def _update_metrics(
        self,
        runtime: LoopView,
        stats: RsiServerStats,
        latencies_ns: np.ndarray,
        jitters_ns: np.ndarray,
        readers: Mapping[int, ReaderMirror],
        rows: list[dict[str, Any]],
    ) -> None:
        new = self._delta("answered", stats.answered)
        if new:
            metrics.RSI_TELEGRAMS.inc(new)
            for v in latencies_ns[-min(new, latencies_ns.size) :]:
                metrics.LOOP_REPLY_LATENCY.observe(float(v) / 1e9)
        new_jitter = self._delta("jitter", stats.jitter.count)
        for v in jitters_ns[-min(new_jitter, jitters_ns.size) :] if new_jitter else ():
            metrics.LOOP_CYCLE_JITTER.observe(abs(float(v)) / 1e9)
        for reason, value in (("garbled", stats.garbled), ("foreign_address", stats.foreign)):
            d = self._delta(f"rejected.{reason}", value)
            if d:
                metrics.RSI_REJECTED.labels(reason=reason).inc(d)
        metrics.LOOP_RUNNING.set(1.0 if runtime.rsi_alive() else 0.0)
        for joint, reader in readers.items():
            for kind, count in reader.fault_counts.items():
                name = _ENCODER_METRIC_KIND.get(str(kind))
                d = self._delta(f"enc.{joint}.{kind}", count)
                if name is not None and d:
                    metrics.encoder_fault_counter(joint, name).inc(d)
            d = self._delta(f"enc.{joint}.warnings", reader.warnings)
            if d:
                metrics.encoder_fault_counter(joint, "warning_bit").inc(d)
        for row in rows:
            j = str(row["joint"])
            metrics.ENCODER_STALE.labels(joint=j).set(0.0 if row["encoder"] == "ok" else 1.0)
            if row["reading_age_ms"] is not None:
                metrics.GRATING_READING_AGE.labels(joint=j).set(row["reading_age_ms"] / 1e3)
            if row["error_deg"] is not None:
                metrics.JOINT_ERROR_RAD.labels(joint=j).set(metrics.radians(row["error_deg"]))
            metrics.JOINT_CORRECTION_RAD.labels(joint=j).set(metrics.radians(row["correction_deg"]))
