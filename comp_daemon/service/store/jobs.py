"""Jobs: fits and diagnoses queued for the worker pool, their progress and results."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from typing import Any

from comp_daemon.service.store.artifacts import ModelStore
from comp_daemon.service.store.records import (
    JOB_FINAL_STATES,
    ConflictError,
    EventRecord,
    JobRecord,
    ModelDraft,
    ModelRecord,
    dumps,
    finite,
    loads,
    record_of,
    without_details,
)

__all__ = ["JobStore"]


class JobStore(ModelStore):
    """The ``jobs`` table (a finished fit stores its model in the same transaction)."""

    @staticmethod
    def _job(row: sqlite3.Row) -> JobRecord:
        return record_of(JobRecord, row, params=json.loads(row["params"]), result=loads(row["result"]))

    def _job_row(self, conn: sqlite3.Connection, job_id: int) -> JobRecord:
        return self._job(self._fetch(conn, "job", job_id))

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
            if dataset_id is not None:
                self._fetch(conn, "dataset", dataset_id, "id")
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
                (kind, dumps(dict(params)), dataset_id, now),
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
        result = without_details("result", "$.stats") if summary else "result"
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
        progress = min(1.0, max(0.0, finite(progress)))
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
        self._notify(listeners, [event])
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
                (dumps(dict(result)), now, job_id),
            )
            model_record = None if model is None else self._insert_model(conn, model, job_id=job_id, now=now)
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
