"""Persistent state of the daemon in one SQLite file: data sets, models, jobs, the target queue, events.

Conventions
- Times are UNIX seconds (float, UTC) from an injectable clock; angles in degrees (``_deg``).
- Every state change is one ``BEGIN IMMEDIATE`` transaction that also appends its row to the
  ``events`` table; listeners (the SSE bus) hear about it only after the commit.
- The file is opened in WAL mode with foreign keys on; ``synchronous=FULL`` (the default) makes a
  committed transaction survive a power cut, ``NORMAL`` only a crash of the process.
- The schema carries a version; ordered migrations are applied at open, each in its own
  transaction, and opening an up-to-date file changes nothing.
- Methods are synchronous and short. One connection is shared under a lock, so a ``Store`` may be
  used from worker threads (``asyncio.to_thread``) and from the event loop.

Target lifecycle::

    queued → compensating → moving → settling → done
       │           └──────────┴─────────┴──→ failed
       └→ cancelled          (at restart) ──→ interrupted → queued (requeue) | cancelled

Recovery (:meth:`Store.recover`, at every start): a target that was compensating, moving or
settling is marked ``interrupted`` for the operator and never redone silently; queued targets keep
their order; jobs that were queued or running fail with "interrupted by a restart".

Modules: :mod:`~.records` (states, errors, records), :mod:`~.schema` (migrations), :mod:`~.base`
(connection, transactions), :mod:`~.artifacts` (data sets, models), :mod:`~.jobs`, :mod:`~.targets`
(batches and the target queue), :mod:`~.events`; :class:`Store` is all of them with recovery.
:mod:`~.files` keeps the files beside the database: the marker, the online backups, the restore
and the daemon's lock.

Faults: a write on a full disk is :class:`StoreFullError` (naming the file and the free space; the
transaction is rolled back whole, nothing stored is lost); a damaged file, or a missing or empty
one where a store existed, is :class:`StoreDamagedError` at open.
"""

from __future__ import annotations

from comp_daemon.service.store.artifacts import DatasetStore, ModelStore
from comp_daemon.service.store.events import EventStore
from comp_daemon.service.store.jobs import JobStore
from comp_daemon.service.store.records import (
    JOB_FINAL_STATES,
    JOB_STATES,
    STATS_DETAIL_PATHS,
    TARGET_ACTIVE_STATES,
    TARGET_FINAL_STATES,
    TARGET_STATES,
    BatchRecord,
    ConflictError,
    DatasetRecord,
    EventListener,
    EventRecord,
    IdempotencyConflict,
    JobRecord,
    ModelDraft,
    ModelRecord,
    NotFoundError,
    RecoveryReport,
    StoreDamagedError,
    StoreError,
    StoreFullError,
    TargetRecord,
    without_details,
)
from comp_daemon.service.store.schema import SCHEMA_VERSION
from comp_daemon.service.store.targets import TargetStore

__all__ = [
    "JOB_FINAL_STATES",
    "JOB_STATES",
    "SCHEMA_VERSION",
    "STATS_DETAIL_PATHS",
    "TARGET_ACTIVE_STATES",
    "TARGET_FINAL_STATES",
    "TARGET_STATES",
    "BatchRecord",
    "ConflictError",
    "DatasetRecord",
    "EventListener",
    "EventRecord",
    "IdempotencyConflict",
    "JobRecord",
    "ModelDraft",
    "ModelRecord",
    "NotFoundError",
    "RecoveryReport",
    "Store",
    "StoreDamagedError",
    "StoreError",
    "StoreFullError",
    "TargetRecord",
    "without_details",
]


class Store(DatasetStore, JobStore, ModelStore, TargetStore, EventStore):
    """The SQLite store. Open with ``Store(path)``; close with :meth:`close` (or use ``with``)."""

    def recover(self) -> RecoveryReport:
        """Bring the store to a consistent state after a start (clean or after a crash)."""
        interrupted = self.interrupt_active(
            "interrupted by a restart of the daemon; check the part before requeueing"
        )
        now = self._clock()
        with self._tx() as conn:
            jobs = conn.execute("SELECT id, kind FROM jobs WHERE state IN ('queued', 'running')").fetchall()
            for job in jobs:
                conn.execute(
                    "UPDATE jobs SET state = 'failed', error = ?, finished_at = ? WHERE id = ?",
                    ("interrupted by a restart of the daemon; start it again", now, job["id"]),
                )
                self._event(
                    conn,
                    "job.failed",
                    {"kind": job["kind"], "error": "interrupted by a restart"},
                    job_id=job["id"],
                    at=now,
                )
            queued = conn.execute("SELECT COUNT(*) FROM targets WHERE state = 'queued'").fetchone()[0]
            self._event(
                conn,
                "store.recovered",
                {
                    "interrupted_targets": interrupted,
                    "queued_targets": queued,
                    "failed_jobs": [j["id"] for j in jobs],
                },
                at=now,
            )
        return RecoveryReport(interrupted, int(queued), [int(j["id"]) for j in jobs])
