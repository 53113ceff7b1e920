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
"""

from __future__ import annotations

import json
import math
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from comp_daemon.common.logs import get_logger

__all__ = [
    "JOB_STATES",
    "SCHEMA_VERSION",
    "TARGET_ACTIVE_STATES",
    "TARGET_FINAL_STATES",
    "TARGET_STATES",
    "BatchRecord",
    "ConflictError",
    "DatasetRecord",
    "EventRecord",
    "IdempotencyConflict",
    "JobRecord",
    "ModelDraft",
    "ModelRecord",
    "NotFoundError",
    "RecoveryReport",
    "Store",
    "StoreError",
    "TargetRecord",
]

TARGET_STATES: tuple[str, ...] = (
    "queued",
    "compensating",
    "moving",
    "settling",
    "done",
    "failed",
    "cancelled",
    "interrupted",
)
TARGET_ACTIVE_STATES: tuple[str, ...] = ("compensating", "moving", "settling")
TARGET_FINAL_STATES: tuple[str, ...] = ("done", "failed", "cancelled")
JOB_STATES: tuple[str, ...] = ("queued", "running", "done", "failed", "cancelled")
JOB_FINAL_STATES: tuple[str, ...] = ("done", "failed", "cancelled")

# allowed moves of a target: from -> to
_TARGET_TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"compensating", "cancelled"}),
    "compensating": frozenset({"moving", "failed", "interrupted"}),
    "moving": frozenset({"settling", "failed", "interrupted"}),
    "settling": frozenset({"done", "failed", "interrupted"}),
    "interrupted": frozenset({"queued", "cancelled"}),
    "done": frozenset(),
    "failed": frozenset(),
    "cancelled": frozenset(),
}


class StoreError(Exception):
    """Base of the errors a caller can act on."""


class NotFoundError(StoreError):
    def __init__(self, what: str, ident: object) -> None:
        self.what = what
        self.ident = ident
        super().__init__(f"{what} {ident} not found")


class ConflictError(StoreError):
    """The request does not fit the current state (a transition that is not allowed, a thing in use)."""


class IdempotencyConflict(ConflictError):
    """The idempotency key was used before with a different request."""


# --------------------------------------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class DatasetRecord:
    id: int
    name: str
    format: Literal["csv", "json"]
    sha256: str
    rows: int
    summary: dict[str, Any]
    created_at: float
    content: str | None = None


@dataclass(frozen=True, slots=True)
class JobRecord:
    id: int
    kind: str
    params: dict[str, Any]
    dataset_id: int | None
    state: str
    progress: float
    message: str | None
    result: dict[str, Any] | None
    error: str | None
    created_at: float
    started_at: float | None
    finished_at: float | None


@dataclass(frozen=True, slots=True)
class ModelDraft:
    """A model about to be stored (the result of a fit)."""

    kind: str
    order: int | None
    artifact: dict[str, Any]
    stats: dict[str, Any]
    dataset_id: int | None


@dataclass(frozen=True, slots=True)
class ModelRecord:
    id: int
    kind: str
    order: int | None
    stats: dict[str, Any]
    dataset_id: int | None
    job_id: int | None
    active: bool
    created_at: float
    artifact: dict[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class BatchRecord:
    id: int
    idempotency_key: str
    request_sha256: str
    source: str | None
    size: int
    created_at: float


@dataclass(frozen=True, slots=True)
class TargetRecord:
    id: int
    batch_id: int
    seq: int
    idempotency_key: str
    queue_pos: int
    request: dict[str, Any]
    state: str
    reason: str | None
    commanded_axes_deg: list[float] | None
    final_joint_errors_deg: dict[str, float | None] | None
    created_at: float
    updated_at: float
    started_at: float | None
    finished_at: float | None


@dataclass(frozen=True, slots=True)
class EventRecord:
    id: int
    time: float
    kind: str
    target_id: int | None
    job_id: int | None
    message: dict[str, Any]


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    interrupted_targets: list[int]
    queued_targets: int
    failed_jobs: list[int]


EventListener = Callable[[EventRecord], None]
_log = get_logger("comp_daemon.store")

# ------------------------------------------------------------------------------------------ migrations

_MIGRATIONS: tuple[tuple[int, tuple[str, ...]], ...] = (
    (
        1,
        (
            """CREATE TABLE datasets (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                name TEXT NOT NULL,
                format TEXT NOT NULL CHECK (format IN ('csv', 'json')),
                content TEXT NOT NULL,
                sha256 TEXT NOT NULL,
                rows INTEGER NOT NULL CHECK (rows >= 0),
                summary TEXT NOT NULL,
                created_at REAL NOT NULL)""",
            """CREATE TABLE jobs (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                kind TEXT NOT NULL,
                params TEXT NOT NULL,
                dataset_id INTEGER REFERENCES datasets(id) ON DELETE SET NULL,
                state TEXT NOT NULL
                    CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
                progress REAL NOT NULL DEFAULT 0,
                message TEXT,
                result TEXT,
                error TEXT,
                created_at REAL NOT NULL,
                started_at REAL,
                finished_at REAL)""",
            "CREATE INDEX jobs_state ON jobs(state)",
            """CREATE TABLE models (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                kind TEXT NOT NULL,
                "order" INTEGER,
                artifact TEXT NOT NULL,
                stats TEXT NOT NULL,
                dataset_id INTEGER REFERENCES datasets(id) ON DELETE SET NULL,
                job_id INTEGER REFERENCES jobs(id) ON DELETE SET NULL,
                active INTEGER NOT NULL DEFAULT 0 CHECK (active IN (0, 1)),
                created_at REAL NOT NULL)""",
            "CREATE UNIQUE INDEX models_one_active ON models(active) WHERE active = 1",
            """CREATE TABLE batches (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                idempotency_key TEXT NOT NULL UNIQUE,
                request_sha256 TEXT NOT NULL,
                source TEXT,
                size INTEGER NOT NULL CHECK (size >= 1),
                created_at REAL NOT NULL)""",
            """CREATE TABLE targets (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                batch_id INTEGER NOT NULL REFERENCES batches(id),
                idempotency_key TEXT NOT NULL UNIQUE,
                seq INTEGER NOT NULL,
                queue_pos INTEGER NOT NULL,
                request TEXT NOT NULL,
                state TEXT NOT NULL CHECK (state IN ('queued', 'compensating', 'moving', 'settling',
                    'done', 'failed', 'cancelled', 'interrupted')),
                reason TEXT,
                commanded_axes TEXT,
                final_joint_errors TEXT,
                created_at REAL NOT NULL,
                updated_at REAL NOT NULL,
                started_at REAL,
                finished_at REAL,
                UNIQUE (batch_id, seq))""",
            "CREATE INDEX targets_state_pos ON targets(state, queue_pos)",
            "CREATE INDEX targets_batch ON targets(batch_id, seq)",
            """CREATE TABLE events (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                time REAL NOT NULL,
                kind TEXT NOT NULL,
                target_id INTEGER REFERENCES targets(id),
                job_id INTEGER REFERENCES jobs(id),
                message TEXT NOT NULL)""",
            "CREATE INDEX events_time ON events(time)",
            "CREATE INDEX events_target ON events(target_id)",
            "CREATE INDEX events_job ON events(job_id)",
        ),
    ),
)
SCHEMA_VERSION = _MIGRATIONS[-1][0]


def _dumps(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), sort_keys=True, allow_nan=False)


#: The bulky entries of fit statistics (per check row, per parameter), left out of list pages by
#: SQLite itself (``json_remove`` runs without Python's GIL, so the real-time thread need not wait
#: for ~1 MB of JSON to be decoded per page of 100 fits).
STATS_DETAIL_PATHS: tuple[str, ...] = (
    "$.errors_3d_mm",
    "$.fit.identifiability",
    "$.fit.identified",
    "$.fit.order_selection",
    "$.fit.range_deg",
    "$.fit.solver",
    "$.fit.effects",
)


def _without_details(column: str, prefix: str = "$") -> str:
    paths = ", ".join(f"'{prefix}{p[1:]}'" for p in STATS_DETAIL_PATHS)
    return f"json_remove({column}, {paths})"


def _loads(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError("not a finite number")
    return float(value)


class Store:
    """The SQLite store. Open with ``Store(path)``; close with :meth:`close` (or use ``with``)."""

    def __init__(
        self,
        path: str | Path,
        *,
        synchronous: Literal["full", "normal"] = "full",
        busy_timeout_ms: int = 5000,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        self._clock = clock
        self._lock = threading.RLock()
        self._listeners: list[EventListener] = []
        self._pending: list[EventRecord] = []
        self._conn = sqlite3.connect(
            str(path), isolation_level=None, check_same_thread=False, timeout=busy_timeout_ms / 1000
        )
        self._conn.row_factory = sqlite3.Row
        mode = self._conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(path) != ":memory:" and str(mode).lower() != "wal":
            raise StoreError(f"cannot put {self.path} in WAL mode (got {mode})")
        self._conn.execute("PRAGMA foreign_keys=ON")
        self._conn.execute(f"PRAGMA synchronous={'FULL' if synchronous == 'full' else 'NORMAL'}")
        self._conn.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
        self._migrate()

    # ------------------------------------------------------------------------------- plumbing

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_listener(self, listener: EventListener) -> None:
        """Call ``listener(event)`` after each committed event (from the committing thread)."""
        with self._lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: EventListener) -> None:
        with self._lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._pending = []
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                self._pending = []
                raise
            events, self._pending = self._pending, []
            listeners = list(self._listeners)
        for event in events:
            for listener in listeners:
                try:
                    listener(event)
                except Exception:  # a listener must never undo or block a committed change
                    _log.exception("event listener failed", event_kind=event.kind)

    def _event(
        self,
        conn: sqlite3.Connection,
        kind: str,
        message: Mapping[str, Any],
        *,
        target_id: int | None = None,
        job_id: int | None = None,
        at: float | None = None,
    ) -> None:
        now = self._clock() if at is None else at
        cur = conn.execute(
            "INSERT INTO events (time, kind, target_id, job_id, message) VALUES (?, ?, ?, ?, ?)",
            (now, kind, target_id, job_id, _dumps(dict(message))),
        )
        assert cur.lastrowid is not None
        self._pending.append(EventRecord(cur.lastrowid, now, kind, target_id, job_id, dict(message)))

    def _read(self, sql: str, args: Sequence[Any] = ()) -> list[sqlite3.Row]:
        with self._lock:
            return self._conn.execute(sql, tuple(args)).fetchall()

    def _migrate(self) -> None:
        with self._lock:
            self._conn.execute(
                "CREATE TABLE IF NOT EXISTS schema_version"
                " (version INTEGER PRIMARY KEY, applied_at REAL NOT NULL)"
            )
            for version, statements in _MIGRATIONS:
                self._conn.execute("BEGIN IMMEDIATE")
                try:
                    done = self._conn.execute(
                        "SELECT 1 FROM schema_version WHERE version = ?", (version,)
                    ).fetchone()
                    if done is None:
                        for statement in statements:
                            self._conn.execute(statement)
                        self._conn.execute(
                            "INSERT INTO schema_version (version, applied_at) VALUES (?, ?)",
                            (version, self._clock()),
                        )
                    self._conn.execute("COMMIT")
                except BaseException:
                    self._conn.execute("ROLLBACK")
                    raise
            newest = self._conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
            if newest is not None and newest > SCHEMA_VERSION:
                raise StoreError(
                    f"{self.path} has schema version {newest}, newer than this program's {SCHEMA_VERSION}"
                )

    def schema_version(self) -> int:
        row = self._read("SELECT MAX(version) AS v FROM schema_version")[0]
        return int(row["v"] or 0)

    # ------------------------------------------------------------------------------- datasets

    @staticmethod
    def _dataset(row: sqlite3.Row, with_content: bool) -> DatasetRecord:
        return DatasetRecord(
            id=row["id"],
            name=row["name"],
            format=row["format"],
            sha256=row["sha256"],
            rows=row["rows"],
            summary=json.loads(row["summary"]),
            created_at=row["created_at"],
            content=row["content"] if with_content else None,
        )

    def add_dataset(
        self,
        *,
        name: str,
        format: Literal["csv", "json"],
        content: str,
        sha256: str,
        rows: int,
        summary: Mapping[str, Any],
    ) -> DatasetRecord:
        now = self._clock()
        with self._tx() as conn:
            cur = conn.execute(
                "INSERT INTO datasets (name, format, content, sha256, rows, summary, created_at)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                (name, format, content, sha256, int(rows), _dumps(dict(summary)), now),
            )
            ident = cur.lastrowid
            assert ident is not None
            self._event(conn, "dataset.added", {"dataset_id": ident, "name": name, "rows": rows}, at=now)
            row = conn.execute("SELECT * FROM datasets WHERE id = ?", (ident,)).fetchone()
        return self._dataset(row, with_content=False)

    def get_dataset(self, dataset_id: int, *, with_content: bool = False) -> DatasetRecord:
        rows = self._read("SELECT * FROM datasets WHERE id = ?", (dataset_id,))
        if not rows:
            raise NotFoundError("dataset", dataset_id)
        return self._dataset(rows[0], with_content)

    def list_datasets(self, *, limit: int = 500, offset: int = 0) -> list[DatasetRecord]:
        rows = self._read("SELECT * FROM datasets ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset))
        return [self._dataset(r, with_content=False) for r in rows]

    def delete_dataset(self, dataset_id: int) -> None:
        """Delete a data set; refused while a queued or running job uses it. Models keep their artifact."""
        with self._tx() as conn:
            if conn.execute("SELECT 1 FROM datasets WHERE id = ?", (dataset_id,)).fetchone() is None:
                raise NotFoundError("dataset", dataset_id)
            busy = conn.execute(
                "SELECT id FROM jobs WHERE dataset_id = ? AND state IN ('queued', 'running')", (dataset_id,)
            ).fetchall()
            if busy:
                raise ConflictError(
                    f"dataset {dataset_id} is used by unfinished job(s) {[r['id'] for r in busy]}"
                )
            conn.execute("DELETE FROM datasets WHERE id = ?", (dataset_id,))
            self._event(conn, "dataset.deleted", {"dataset_id": dataset_id})

    # ----------------------------------------------------------------------------------- jobs

    @staticmethod
    def _job(row: sqlite3.Row) -> JobRecord:
        return JobRecord(
            id=row["id"],
            kind=row["kind"],
            params=json.loads(row["params"]),
            dataset_id=row["dataset_id"],
            state=row["state"],
            progress=row["progress"],
            message=row["message"],
            result=_loads(row["result"]),
            error=row["error"],
            created_at=row["created_at"],
            started_at=row["started_at"],
            finished_at=row["finished_at"],
        )

    def _job_row(self, conn: sqlite3.Connection, job_id: int) -> JobRecord:
        row = conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise NotFoundError("job", job_id)
        return self._job(row)

    def create_job(
        self,
        kind: str,
        params: Mapping[str, Any],
        *,
        dataset_id: int | None = None,
        max_pending: int | None = None,
    ) -> JobRecord:
        """A queued job; refused (``ConflictError``) when ``max_pending`` jobs are already unfinished."""
        now = self._clock()
        with self._tx() as conn:
            if dataset_id is not None and (
                conn.execute("SELECT 1 FROM datasets WHERE id = ?", (dataset_id,)).fetchone() is None
            ):
                raise NotFoundError("dataset", dataset_id)
            if max_pending is not None:
                pending = conn.execute(
                    "SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')"
                ).fetchone()[0]
                if pending >= max_pending:
                    raise ConflictError(
                        f"{pending} jobs are unfinished (limit jobs.max_pending = {max_pending})"
                    )
            cur = conn.execute(
                "INSERT INTO jobs (kind, params, dataset_id, state, progress, created_at)"
                " VALUES (?, ?, ?, 'queued', 0, ?)",
                (kind, _dumps(dict(params)), dataset_id, now),
            )
            assert cur.lastrowid is not None
            job = self._job_row(conn, cur.lastrowid)
            self._event(conn, "job.queued", {"kind": kind, "dataset_id": dataset_id}, job_id=job.id, at=now)
        return job

    def get_job(self, job_id: int) -> JobRecord:
        with self._lock:
            return self._job_row(self._conn, job_id)

    def list_jobs(
        self,
        *,
        kind: str | None = None,
        state: str | None = None,
        limit: int = 500,
        offset: int = 0,
        summary: bool = False,
    ) -> list[JobRecord]:
        """Jobs, newest first; ``summary``: results without :data:`STATS_DETAIL_PATHS` under ``stats``."""
        result = _without_details("result", "$.stats") if summary else "result"
        sql = (
            "SELECT id, kind, params, dataset_id, state, progress, message, "
            f"{result} AS result, error, created_at, started_at, finished_at FROM jobs WHERE 1=1"
        )
        args = list[Any]()
        if kind is not None:
            sql += " AND kind = ?"
            args.append(kind)
        if state is not None:
            sql += " AND state = ?"
            args.append(state)
        sql += " ORDER BY id DESC LIMIT ? OFFSET ?"
        args += [limit, offset]
        return [self._job(r) for r in self._read(sql, args)]

    def start_job(self, job_id: int) -> JobRecord:
        now = self._clock()
        with self._tx() as conn:
            job = self._job_row(conn, job_id)
            if job.state != "queued":
                raise ConflictError(f"job {job_id} is {job.state}, not queued")
            conn.execute("UPDATE jobs SET state = 'running', started_at = ? WHERE id = ?", (now, job_id))
            self._event(conn, "job.running", {"kind": job.kind}, job_id=job_id, at=now)
            return self._job_row(conn, job_id)

    def set_job_progress(self, job_id: int, progress: float, message: str | None = None) -> bool:
        """Record progress (0..1) of a running job; False if the job is no longer running.

        Progress is not written to the event log; listeners hear it as a ``job.progress`` event with id 0.
        """
        progress = min(1.0, max(0.0, _finite(progress)))
        with self._lock:
            cur = self._conn.execute(
                "UPDATE jobs SET progress = ?, message = ? WHERE id = ? AND state = 'running'",
                (progress, message, job_id),
            )
            listeners = list(self._listeners)
        if cur.rowcount != 1:
            return False
        event = EventRecord(
            0, self._clock(), "job.progress", None, job_id, {"progress": progress, "message": message}
        )
        for listener in listeners:
            try:
                listener(event)
            except Exception:
                _log.exception("event listener failed", event_kind=event.kind)
        return True

    def finish_job(
        self, job_id: int, result: Mapping[str, Any], *, model: ModelDraft | None = None
    ) -> tuple[JobRecord, ModelRecord | None]:
        """Mark a running job done with its result, storing ``model`` in the same transaction."""
        now = self._clock()
        with self._tx() as conn:
            job = self._job_row(conn, job_id)
            if job.state != "running":
                raise ConflictError(f"job {job_id} is {job.state}, not running")
            conn.execute(
                "UPDATE jobs SET state = 'done', progress = 1, result = ?, finished_at = ? WHERE id = ?",
                (_dumps(dict(result)), now, job_id),
            )
            model_record = None
            if model is not None:
                cur = conn.execute(
                    'INSERT INTO models (kind, "order", artifact, stats, dataset_id, job_id, active,'
                    " created_at)"
                    " VALUES (?, ?, ?, ?, ?, ?, 0, ?)",
                    (
                        model.kind,
                        model.order,
                        _dumps(model.artifact),
                        _dumps(model.stats),
                        model.dataset_id,
                        job_id,
                        now,
                    ),
                )
                assert cur.lastrowid is not None
                model_record = self._model_row(conn, cur.lastrowid, with_artifact=False)
                self._event(
                    conn,
                    "model.added",
                    {"model_id": model_record.id, "kind": model.kind, "order": model.order},
                    job_id=job_id,
                    at=now,
                )
            self._event(conn, "job.done", {"kind": job.kind}, job_id=job_id, at=now)
            return self._job_row(conn, job_id), model_record

    def fail_job(self, job_id: int, error: str) -> JobRecord:
        now = self._clock()
        with self._tx() as conn:
            job = self._job_row(conn, job_id)
            if job.state in JOB_FINAL_STATES:
                raise ConflictError(f"job {job_id} is already {job.state}")
            conn.execute(
                "UPDATE jobs SET state = 'failed', error = ?, finished_at = ? WHERE id = ?",
                (error, now, job_id),
            )
            self._event(conn, "job.failed", {"kind": job.kind, "error": error}, job_id=job_id, at=now)
            return self._job_row(conn, job_id)

    def cancel_job(self, job_id: int, *, by: str | None = None) -> JobRecord:
        now = self._clock()
        with self._tx() as conn:
            job = self._job_row(conn, job_id)
            if job.state in JOB_FINAL_STATES:
                raise ConflictError(f"job {job_id} is already {job.state}")
            conn.execute("UPDATE jobs SET state = 'cancelled', finished_at = ? WHERE id = ?", (now, job_id))
            self._event(conn, "job.cancelled", {"kind": job.kind, "by": by}, job_id=job_id, at=now)
            return self._job_row(conn, job_id)

    # --------------------------------------------------------------------------------- models

    @staticmethod
    def _model(row: sqlite3.Row, with_artifact: bool) -> ModelRecord:
        return ModelRecord(
            id=row["id"],
            kind=row["kind"],
            order=row["order"],
            stats=json.loads(row["stats"]),
            dataset_id=row["dataset_id"],
            job_id=row["job_id"],
            active=bool(row["active"]),
            created_at=row["created_at"],
            artifact=json.loads(row["artifact"]) if with_artifact else None,
        )

    def _model_row(self, conn: sqlite3.Connection, model_id: int, *, with_artifact: bool) -> ModelRecord:
        row = conn.execute("SELECT * FROM models WHERE id = ?", (model_id,)).fetchone()
        if row is None:
            raise NotFoundError("model", model_id)
        return self._model(row, with_artifact)

    def add_model(self, draft: ModelDraft) -> ModelRecord:
        """Store a model that did not come from a job (an imported artifact)."""
        now = self._clock()
        with self._tx() as conn:
            cur = conn.execute(
                'INSERT INTO models (kind, "order", artifact, stats, dataset_id, job_id, active, created_at)'
                " VALUES (?, ?, ?, ?, ?, NULL, 0, ?)",
                (draft.kind, draft.order, _dumps(draft.artifact), _dumps(draft.stats), draft.dataset_id, now),
            )
            assert cur.lastrowid is not None
            record = self._model_row(conn, cur.lastrowid, with_artifact=False)
            self._event(
                conn, "model.added", {"model_id": record.id, "kind": draft.kind, "order": draft.order}
            )
        return record

    def get_model(self, model_id: int, *, with_artifact: bool = False) -> ModelRecord:
        with self._lock:
            return self._model_row(self._conn, model_id, with_artifact=with_artifact)

    def list_models(self, *, limit: int = 500, offset: int = 0, summary: bool = False) -> list[ModelRecord]:
        """Models without artifacts, newest first; ``summary``: stats without :data:`STATS_DETAIL_PATHS`."""
        stats = _without_details("stats") if summary else "stats"
        rows = self._read(
            f'SELECT id, kind, "order", {stats} AS stats, dataset_id, job_id, active, created_at '
            "FROM models ORDER BY id DESC LIMIT ? OFFSET ?",
            (limit, offset),
        )
        return [self._model(r, with_artifact=False) for r in rows]

    def active_model(self, *, with_artifact: bool = True) -> ModelRecord | None:
        rows = self._read("SELECT * FROM models WHERE active = 1")
        return self._model(rows[0], with_artifact) if rows else None

    def activate_model(self, model_id: int, *, by: str | None = None) -> ModelRecord:
        with self._tx() as conn:
            self._model_row(conn, model_id, with_artifact=False)
            previous = conn.execute("SELECT id FROM models WHERE active = 1").fetchone()
            conn.execute("UPDATE models SET active = 0 WHERE active = 1")
            conn.execute("UPDATE models SET active = 1 WHERE id = ?", (model_id,))
            self._event(
                conn,
                "model.activated",
                {"model_id": model_id, "previous_model_id": previous["id"] if previous else None, "by": by},
            )
            return self._model_row(conn, model_id, with_artifact=False)

    # -------------------------------------------------------------------------- batches/targets

    @staticmethod
    def _batch(row: sqlite3.Row) -> BatchRecord:
        return BatchRecord(
            id=row["id"],
            idempotency_key=row["idempotency_key"],
            request_sha256=row["request_sha256"],
            source=row["source"],
            size=row["size"],
            created_at=row["created_at"],
        )

    @staticmethod
    def _target(row: sqlite3.Row) -> TargetRecord:
        return TargetRecord(
            id=row["id"],
            batch_id=row["batch_id"],
            seq=row["seq"],
            idempotency_key=row["idempotency_key"],
            queue_pos=row["queue_pos"],
            request=json.loads(row["request"]),
            state=row["state"],
            reason=row["reason"],
            commanded_axes_deg=_loads(row["commanded_axes"]),
            final_joint_errors_deg=_loads(row["final_joint_errors"]),
            created_at=row["created_at"],
            updated_at=row["updated_at"],
            started_at=row["started_at"],
            finished_at=row["finished_at"],
        )

    def _target_row(self, conn: sqlite3.Connection, target_id: int) -> TargetRecord:
        row = conn.execute("SELECT * FROM targets WHERE id = ?", (target_id,)).fetchone()
        if row is None:
            raise NotFoundError("target", target_id)
        return self._target(row)

    def _batch_targets(self, conn: sqlite3.Connection, batch_id: int) -> list[TargetRecord]:
        rows = conn.execute("SELECT * FROM targets WHERE batch_id = ? ORDER BY seq", (batch_id,)).fetchall()
        return [self._target(r) for r in rows]

    def submit_batch(
        self,
        idempotency_key: str,
        request_sha256: str,
        targets: Sequence[Mapping[str, Any]],
        *,
        source: str | None = None,
    ) -> tuple[BatchRecord, list[TargetRecord], bool]:
        """Queue a batch of targets once per idempotency key.

        Returns ``(batch, targets, created)``. The same key with the same request hash returns the
        stored batch (``created`` False); with another hash it raises :class:`IdempotencyConflict`.
        The batch and all its targets are committed together or not at all.
        """
        if not targets:
            raise ValueError("a batch needs at least one target")
        now = self._clock()
        with self._tx() as conn:
            row = conn.execute(
                "SELECT * FROM batches WHERE idempotency_key = ?", (idempotency_key,)
            ).fetchone()
            if row is not None:
                batch = self._batch(row)
                if batch.request_sha256 != request_sha256:
                    raise IdempotencyConflict(
                        f"Idempotency-Key {idempotency_key!r} was used for batch {batch.id}"
                        " with a different body"
                    )
                return batch, self._batch_targets(conn, batch.id), False
            cur = conn.execute(
                "INSERT INTO batches (idempotency_key, request_sha256, source, size, created_at)"
                " VALUES (?, ?, ?, ?, ?)",
                (idempotency_key, request_sha256, source, len(targets), now),
            )
            batch_id = cur.lastrowid
            assert batch_id is not None
            pos = conn.execute("SELECT COALESCE(MAX(queue_pos), 0) FROM targets").fetchone()[0]
            conn.executemany(
                "INSERT INTO targets (batch_id, idempotency_key, seq, queue_pos, request, state, created_at,"
                " updated_at) VALUES (?, ?, ?, ?, ?, 'queued', ?, ?)",
                [
                    (batch_id, f"{idempotency_key}#{seq}", seq, pos + seq, _dumps(dict(t)), now, now)
                    for seq, t in enumerate(targets, start=1)
                ],
            )
            batch = self._batch(conn.execute("SELECT * FROM batches WHERE id = ?", (batch_id,)).fetchone())
            stored = self._batch_targets(conn, batch_id)
            self._event(
                conn,
                "batch.accepted",
                {
                    "batch_id": batch_id,
                    "size": len(stored),
                    "first_target_id": stored[0].id,
                    "last_target_id": stored[-1].id,
                    "source": source,
                },
                at=now,
            )
        return batch, stored, True

    def get_batch(self, batch_id: int) -> tuple[BatchRecord, list[TargetRecord]]:
        with self._lock:
            row = self._conn.execute("SELECT * FROM batches WHERE id = ?", (batch_id,)).fetchone()
            if row is None:
                raise NotFoundError("batch", batch_id)
            return self._batch(row), self._batch_targets(self._conn, batch_id)

    def find_batch(self, idempotency_key: str) -> BatchRecord | None:
        rows = self._read("SELECT * FROM batches WHERE idempotency_key = ?", (idempotency_key,))
        return self._batch(rows[0]) if rows else None

    def get_target(self, target_id: int) -> TargetRecord:
        with self._lock:
            return self._target_row(self._conn, target_id)

    def list_targets(
        self,
        *,
        batch_id: int | None = None,
        states: Sequence[str] | None = None,
        limit: int = 500,
        offset: int = 0,
        newest_first: bool = False,
    ) -> list[TargetRecord]:
        sql, args = "SELECT * FROM targets WHERE 1=1", list[Any]()
        if batch_id is not None:
            sql += " AND batch_id = ?"
            args.append(batch_id)
        if states:
            sql += f" AND state IN ({', '.join('?' * len(states))})"
            args += list(states)
        sql += f" ORDER BY {'id DESC' if newest_first else 'queue_pos, id'} LIMIT ? OFFSET ?"
        args += [limit, offset]
        return [self._target(r) for r in self._read(sql, args)]

    def target_counts(self) -> dict[str, int]:
        counts = dict.fromkeys(TARGET_STATES, 0)
        for row in self._read("SELECT state, COUNT(*) AS n FROM targets GROUP BY state"):
            counts[row["state"]] = row["n"]
        return counts

    def queue_depth(self) -> int:
        return int(self._read("SELECT COUNT(*) AS n FROM targets WHERE state = 'queued'")[0]["n"])

    def _move_target(
        self,
        conn: sqlite3.Connection,
        target: TargetRecord,
        state: str,
        *,
        reason: str | None,
        extra: Mapping[str, Any] | None = None,
        set_sql: str = "",
        set_args: Sequence[Any] = (),
    ) -> TargetRecord:
        if state not in _TARGET_TRANSITIONS[target.state]:
            raise ConflictError(f"target {target.id} is {target.state}; it cannot become {state}")
        now = self._clock()
        started = ", started_at = COALESCE(started_at, ?)" if state == "compensating" else ""
        finished = ", finished_at = ?" if state in TARGET_FINAL_STATES else ""
        args: list[Any] = [state, reason, now]
        if started:
            args.append(now)
        if finished:
            args.append(now)
        conn.execute(
            f"UPDATE targets SET state = ?, reason = ?, updated_at = ?{started}{finished}{set_sql}"
            " WHERE id = ?",
            (*args, *set_args, target.id),
        )
        message: dict[str, Any] = {"batch_id": target.batch_id, "from": target.state, "to": state}
        if reason is not None:
            message["reason"] = reason
        if extra:
            message.update(extra)
        self._event(conn, f"target.{state}", message, target_id=target.id, at=now)
        return self._target_row(conn, target.id)

    def claim_next_target(self) -> TargetRecord | None:
        """Take the first queued target (queue order) and mark it ``compensating``; None if none is queued."""
        with self._tx() as conn:
            row = conn.execute(
                "SELECT * FROM targets WHERE state = 'queued' ORDER BY queue_pos, id LIMIT 1"
            ).fetchone()
            if row is None:
                return None
            return self._move_target(conn, self._target(row), "compensating", reason=None)

    def advance_target(
        self,
        target_id: int,
        state: str,
        *,
        reason: str | None = None,
        commanded_axes_deg: Sequence[float] | None = None,
        final_joint_errors_deg: Mapping[str, float | None] | None = None,
    ) -> TargetRecord:
        """Move a target along its lifecycle (the daemon's call); refused for moves not in the diagram."""
        if state not in TARGET_STATES:
            raise ValueError(f"unknown target state {state!r}")
        set_sql, set_args, extra = "", list[Any](), dict[str, Any]()
        if commanded_axes_deg is not None:
            axes = [_finite(float(a)) for a in commanded_axes_deg]
            set_sql += ", commanded_axes = ?"
            set_args.append(_dumps(axes))
            extra["commanded_axes_deg"] = axes
        if final_joint_errors_deg is not None:
            errors = {
                str(k): (None if v is None else _finite(float(v))) for k, v in final_joint_errors_deg.items()
            }
            set_sql += ", final_joint_errors = ?"
            set_args.append(_dumps(errors))
            extra["final_joint_errors_deg"] = errors
        with self._tx() as conn:
            target = self._target_row(conn, target_id)
            return self._move_target(
                conn, target, state, reason=reason, extra=extra, set_sql=set_sql, set_args=set_args
            )

    def cancel_target(self, target_id: int, *, by: str | None = None) -> TargetRecord:
        """Cancel a target that has not started (queued) or was interrupted."""
        with self._tx() as conn:
            target = self._target_row(conn, target_id)
            if target.state not in ("queued", "interrupted"):
                raise ConflictError(
                    f"target {target_id} is {target.state};"
                    " only queued or interrupted targets can be cancelled"
                )
            return self._move_target(conn, target, "cancelled", reason=f"cancelled by {by or 'request'}")

    def cancel_batch(self, batch_id: int, *, by: str | None = None) -> list[TargetRecord]:
        """Cancel every queued target of a batch; returns the ones cancelled."""
        with self._tx() as conn:
            if conn.execute("SELECT 1 FROM batches WHERE id = ?", (batch_id,)).fetchone() is None:
                raise NotFoundError("batch", batch_id)
            rows = conn.execute(
                "SELECT * FROM targets WHERE batch_id = ? AND state = 'queued' ORDER BY seq", (batch_id,)
            ).fetchall()
            return [
                self._move_target(
                    conn, self._target(r), "cancelled", reason=f"cancelled by {by or 'request'}"
                )
                for r in rows
            ]

    def requeue_target(self, target_id: int, *, by: str | None = None) -> TargetRecord:
        """Put an interrupted target back at the end of the queue (an operator's decision)."""
        with self._tx() as conn:
            target = self._target_row(conn, target_id)
            if target.state != "interrupted":
                raise ConflictError(
                    f"target {target_id} is {target.state}; only interrupted targets can be requeued"
                )
            pos = conn.execute("SELECT COALESCE(MAX(queue_pos), 0) FROM targets").fetchone()[0]
            return self._move_target(
                conn,
                target,
                "queued",
                reason=f"requeued by {by or 'request'} after interruption",
                set_sql=(
                    ", queue_pos = ?, started_at = NULL, commanded_axes = NULL, final_joint_errors = NULL"
                ),
                set_args=[pos + 1],
            )

    def interrupt_active(self, reason: str) -> list[int]:
        """Mark every compensating/moving/settling target ``interrupted``; returns their ids."""
        with self._tx() as conn:
            rows = conn.execute(
                "SELECT * FROM targets WHERE state IN ('compensating', 'moving', 'settling')"
                " ORDER BY queue_pos"
            ).fetchall()
            return [self._move_target(conn, self._target(r), "interrupted", reason=reason).id for r in rows]

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

    # --------------------------------------------------------------------------------- events

    @staticmethod
    def _event_record(row: sqlite3.Row) -> EventRecord:
        return EventRecord(
            id=row["id"],
            time=row["time"],
            kind=row["kind"],
            target_id=row["target_id"],
            job_id=row["job_id"],
            message=json.loads(row["message"]),
        )

    def add_event(
        self,
        kind: str,
        message: Mapping[str, Any],
        *,
        target_id: int | None = None,
        job_id: int | None = None,
    ) -> None:
        """Append an event that is not a state change of this store (the daemon's faults, for instance)."""
        with self._tx() as conn:
            self._event(conn, kind, message, target_id=target_id, job_id=job_id)

    def list_events(
        self,
        *,
        after_id: int = 0,
        limit: int = 100,
        target_id: int | None = None,
        job_id: int | None = None,
        newest_first: bool = False,
    ) -> list[EventRecord]:
        sql, args = "SELECT * FROM events WHERE id > ?", [after_id]
        if target_id is not None:
            sql += " AND target_id = ?"
            args.append(target_id)
        if job_id is not None:
            sql += " AND job_id = ?"
            args.append(job_id)
        sql += f" ORDER BY id {'DESC' if newest_first else 'ASC'} LIMIT ?"
        args.append(limit)
        return [self._event_record(r) for r in self._read(sql, args)]

    def prune_events(self, older_than_s: float) -> int:
        """Delete events older than ``older_than_s`` seconds; returns how many."""
        cutoff = self._clock() - older_than_s
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                n = self._conn.execute("DELETE FROM events WHERE time < ?", (cutoff,)).rowcount
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
        return int(n)
