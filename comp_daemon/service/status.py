"""The service's status, built at a fixed rate and served as it is: :class:`StatusBoard`.

``/api/status`` (what the dashboard shows), ``/ready`` and the dashboard's ready light all read the
board's latest snapshot, so they always agree, and a request costs the copy of a few kilobytes
instead of five store queries: with 50 clients polling, the store and the worker threads see one
build every ``http.status_interval_s`` (0.25 s), whatever the number of readers. A snapshot is at most
that old, except after a change in the store (a model activated, a target queued or finished, a job
started): the first request after it waits for a new build (:meth:`StatusBoard.changed`, called by
the store's event listener), so a client that changed something sees it at once. Should the building
task stall, a request finding a snapshot older than ``4 × status_interval_s`` builds one itself.
Requests that need a build meanwhile all wait for the same one.

**The ready rule** (:func:`readiness_reasons`), one for all three: the daemon's own reasons (loop not
running, a stop fault latched, an encoder stale, no grating calibration, no motion port, a
calibration in progress), a fault of any kind still latched (``state`` is ``fault``: the next
target clears a freeze fault, an operator clears a stop fault with ``POST /api/loop/reset-fault``),
no active model, and a store that cannot write ("store not writable: …", from
:meth:`~comp_daemon.service.store.Store.write_problem`: a full disk, said until a write works
again). Ready means no reason.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from typing import Any, Protocol, runtime_checkable

from comp_daemon import __version__
from comp_daemon.common.logs import get_logger
from comp_daemon.service.daemon_view import DaemonSnapshot
from comp_daemon.service.schemas import ModelOut
from comp_daemon.service.state import ServiceState

__all__ = ["NO_MODEL", "RsiReporter", "StatusBoard", "readiness_reasons"]

_log = get_logger("comp_daemon.api.status")

NO_MODEL = "no model is active"
FAULT_LATCHED = "a fault is latched"


@runtime_checkable
class RsiReporter(Protocol):
    """A daemon view that tracks the RSI sessions (the daemon's ``CellView``)."""

    def rsi_report(self) -> dict[str, Any]:
        """``running``, ``sessions``, ``stops_total``, ``stops_by_cause``, ``rearms``, ``next`` and
        ``stops`` (newest first: ``time``, ``cause``, ``detail``, ``cycles``, ``late_replies``, ``next``…)."""
        ...


def readiness_reasons(
    daemon_reasons: list[str], snapshot: DaemonSnapshot, model_active: bool, store_problem: str | None = None
) -> list[str]:
    """Why the service is not ready (empty: ready); see the module docstring."""
    reasons = list(daemon_reasons)
    if store_problem is not None:
        reasons.append(store_problem)
    if snapshot.state == "fault" and not any("fault latched" in r for r in reasons):
        reasons.append(
            f"{FAULT_LATCHED} ({snapshot.hold_reason or 'no detail'}); the next target clears it, "
            "or an operator with POST /api/loop/reset-fault"
        )
    if not model_active:
        reasons.append(NO_MODEL)
    return reasons


class StatusBoard:
    """The latest status snapshot of a service; :meth:`run` keeps it fresh (see the module docstring)."""

    def __init__(self, svc: ServiceState, interval_s: float) -> None:
        self.svc = svc
        self.interval_s = interval_s
        self.doc: dict[str, Any] = {}
        self.body = b"{}"
        self.built_at = -float("inf")  # monotonic seconds
        self._generation = 0  # store changes seen (changed())
        self._built_generation = -1  # the generation the snapshot includes
        self._building: asyncio.Task[None] | None = None

    def changed(self) -> None:
        """The store changed: the next request waits for a snapshot built after now (any thread)."""
        self._generation += 1

    async def build(self) -> None:
        """Build a new snapshot now (requests that come meanwhile wait for this one)."""
        if self._building is None or self._building.done():
            self._building = asyncio.create_task(self._build())
        await asyncio.shield(self._building)

    async def _build(self) -> None:
        svc = self.svc
        generation = self._generation
        snapshot = svc.daemon.snapshot()
        daemon_reasons = list(svc.daemon.readiness_reasons())
        counts, active, jobs, store_problem = await svc.run(self._store_part)
        reasons = readiness_reasons(daemon_reasons, snapshot, active is not None, store_problem)
        doc = {
            "version": __version__,
            "robot": svc.robot.name,
            "cycle_ms": svc.settings.rsi.cycle_ms,
            "controller": {
                "settle_tolerance_deg": svc.settings.controller.settle_tolerance_deg,
                "rough_threshold_deg": svc.settings.controller.rough_threshold_deg,
            },
            "daemon": snapshot.to_dict(),
            "rsi": svc.daemon.rsi_report() if isinstance(svc.daemon, RsiReporter) else None,
            "ready": not reasons,
            "reasons": reasons,
            "targets": counts,
            "active_model": active,
            "jobs": jobs,
            "job_kinds": svc.runner.kinds(),
            "built_at": time.time(),
        }
        self.body = json.dumps(doc, default=str, allow_nan=False).encode()
        self.doc = doc
        self.built_at = time.monotonic()
        self._built_generation = generation

    def _store_part(self) -> tuple[dict[str, int], dict[str, Any] | None, dict[str, int], str | None]:
        """Target counts, the active model (summary), job counts and whether the store can write, in
        one worker thread."""
        store = self.svc.store
        store_problem = store.write_problem()
        counts = store.target_counts()
        active = store.active_model(with_artifact=False)
        running = len(store.list_jobs(state="running", limit=50))
        queued = len(store.list_jobs(state="queued", limit=50))
        model = ModelOut.of(active, summary=True).model_dump() if active is not None else None
        return counts, model, {"running": running, "queued": queued}, store_problem

    async def current(self) -> dict[str, Any]:
        """The latest snapshot, built here after a store change or if older than four intervals."""
        for _ in range(2):  # a build under way may have started before the change
            stale = time.monotonic() - self.built_at > 4 * self.interval_s
            if not stale and self._built_generation >= self._generation:
                break
            await self.build()
        return self.doc

    async def current_body(self) -> bytes:
        """The latest snapshot as JSON bytes (see :meth:`current`)."""
        await self.current()
        return self.body

    async def run(self) -> None:
        """Build a snapshot every ``interval_s`` until cancelled (a failed build is logged and retried)."""
        while True:
            try:
                await self.build()
            except asyncio.CancelledError:
                raise
            except Exception:
                _log.exception("status snapshot failed")
            await asyncio.sleep(self.interval_s)

    async def stop(self, task: asyncio.Task[None]) -> None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        if self._building is not None and not self._building.done():
            self._building.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._building
