"""Data sets and models: uploaded measurement files, fitted (or imported) models and the active one."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from typing import Any, Literal

from comp_daemon.service.store.base import StoreBase
from comp_daemon.service.store.records import (
    ConflictError,
    DatasetRecord,
    ModelDraft,
    ModelRecord,
    NotFoundError,
    dumps,
    record_of,
    without_details,
)

__all__ = ["DatasetContent", "DatasetStore", "ModelStore"]

#: the columns of a data set without its content (list pages, descriptions)
_DATASET_META = "id, name, format, sha256, rows, summary, created_at"
#: the columns of a model without its artifact
_MODEL_META = 'id, kind, "order", stats, dataset_id, job_id, active, created_at'


class DatasetContent:
    """A stored data set's CSV, read a chunk at a time (``size`` bytes of UTF-8 in all).

    On a database file the chunks come from a read-only connection of its own, in one read
    transaction: the download is the content as it was when it was opened, even if the data set is
    deleted meanwhile, and the shared connection's lock is never held for it. On ``:memory:`` each
    chunk is read under the store's lock. Blocking: call :meth:`read` and :meth:`close` in a worker
    thread.
    """

    def __init__(self, store: StoreBase, dataset_id: int) -> None:
        self._store = store
        self._id = dataset_id
        self._pos = 0
        self._conn: sqlite3.Connection | None = None
        self._blob: sqlite3.Blob | None = None
        if str(store.path) != ":memory:":
            self._conn = sqlite3.connect(
                f"{store.path.resolve().as_uri()}?mode=ro", uri=True, isolation_level=None,
                check_same_thread=False,
            )  # fmt: skip
            try:
                # a blob is read past the page cache: keep this connection's cache small (64 KiB, not
                # the default 2 MB), since each download in flight has a connection of its own
                self._conn.execute("PRAGMA cache_size=-64")
                self._conn.execute("BEGIN")
                self._blob = self._open(self._conn)
                self.size = len(self._blob)
            except BaseException:
                self._conn.close()
                raise
        else:
            with store._lock:
                blob = self._open(store._conn)
                with blob:
                    self.size = len(blob)

    def _open(self, conn: sqlite3.Connection) -> sqlite3.Blob:
        try:
            return conn.blobopen("datasets", "content", self._id, readonly=True)
        except sqlite3.OperationalError:  # no such row
            raise NotFoundError("dataset", self._id) from None

    def read(self, n: int) -> bytes:
        """The next ``n`` bytes at most (b"" at the end)."""
        if self._blob is not None:
            return self._blob.read(n)
        with self._store._lock:
            with self._open(self._store._conn) as blob:
                blob.seek(self._pos)
                chunk = blob.read(n)
        self._pos += len(chunk)
        return chunk

    def close(self) -> None:
        if self._blob is not None:
            self._blob.close()
            self._blob = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None


class DatasetStore(StoreBase):
    """The ``datasets`` table."""

    @staticmethod
    def _dataset(row: sqlite3.Row, with_content: bool) -> DatasetRecord:
        content = row["content"] if with_content else None  # read only when asked for
        return record_of(DatasetRecord, row, summary=json.loads(row["summary"]), content=content)

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
                (name, format, content, sha256, int(rows), dumps(dict(summary)), now),
            )
            ident = cur.lastrowid
            assert ident is not None
            self._event(conn, "dataset.added", {"dataset_id": ident, "name": name, "rows": rows}, at=now)
            row = self._fetch(conn, "dataset", ident)
        return self._dataset(row, with_content=False)

    def get_dataset(self, dataset_id: int, *, with_content: bool = False) -> DatasetRecord:
        columns = "*" if with_content else _DATASET_META
        with self._lock:
            return self._dataset(self._fetch(self._conn, "dataset", dataset_id, columns), with_content)

    def list_datasets(self, *, limit: int = 500, offset: int = 0) -> list[DatasetRecord]:
        """Data sets without their content (metadata only), newest first."""
        rows = self._read(
            f"SELECT {_DATASET_META} FROM datasets ORDER BY id DESC LIMIT ? OFFSET ?", (limit, offset)
        )
        return [self._dataset(r, with_content=False) for r in rows]

    def open_dataset_content(self, dataset_id: int) -> DatasetContent:
        """The data set's stored CSV to read in chunks (NotFoundError if there is none)."""
        return DatasetContent(self, dataset_id)

    def delete_dataset(self, dataset_id: int) -> None:
        """Delete a data set; refused while a queued or running job uses it. Models keep their artifact."""
        with self._tx() as conn:
            self._fetch(conn, "dataset", dataset_id, "id")
            busy = conn.execute(
                "SELECT id FROM jobs WHERE dataset_id = ? AND state IN ('queued', 'running')", (dataset_id,)
            ).fetchall()
            if busy:
                raise ConflictError(
                    f"dataset {dataset_id} is used by unfinished job(s) {[r['id'] for r in busy]}"
                )
            conn.execute("DELETE FROM datasets WHERE id = ?", (dataset_id,))
            self._event(conn, "dataset.deleted", {"dataset_id": dataset_id})


class ModelStore(StoreBase):
    """The ``models`` table; exactly one model at most is active."""

    @staticmethod
    def _model(row: sqlite3.Row, with_artifact: bool) -> ModelRecord:
        artifact = json.loads(row["artifact"]) if with_artifact else None
        return record_of(
            ModelRecord, row, stats=json.loads(row["stats"]), active=bool(row["active"]), artifact=artifact
        )

    def _model_row(self, conn: sqlite3.Connection, model_id: int, *, with_artifact: bool) -> ModelRecord:
        columns = "*" if with_artifact else _MODEL_META
        return self._model(self._fetch(conn, "model", model_id, columns), with_artifact)

    def add_model(self, draft: ModelDraft) -> ModelRecord:
        """Store a model that did not come from a job (an imported artifact)."""
        now = self._clock()
        with self._tx() as conn:
            return self._insert_model(conn, draft, job_id=None, now=now)

    def _insert_model(
        self, conn: sqlite3.Connection, draft: ModelDraft, *, job_id: int | None, now: float
    ) -> ModelRecord:
        """Insert ``draft`` (inactive) and log ``model.added``, inside the caller's transaction."""
        cur = conn.execute(
            'INSERT INTO models (kind, "order", artifact, stats, dataset_id, job_id, active, created_at)'
            " VALUES (?, ?, ?, ?, ?, ?, 0, ?)",
            (
                draft.kind,
                draft.order,
                dumps(draft.artifact),
                dumps(draft.stats),
                draft.dataset_id,
                job_id,
                now,
            ),
        )
        assert cur.lastrowid is not None
        record = self._model_row(conn, cur.lastrowid, with_artifact=False)
        self._event(
            conn,
            "model.added",
            {"model_id": record.id, "kind": draft.kind, "order": draft.order},
            job_id=job_id,
            at=now,
        )
        return record

    def get_model(self, model_id: int, *, with_artifact: bool = False) -> ModelRecord:
        with self._lock:
            return self._model_row(self._conn, model_id, with_artifact=with_artifact)

    def list_models(self, *, limit: int = 500, offset: int = 0, summary: bool = False) -> list[ModelRecord]:
        """Models without artifacts, newest first; ``summary``: stats without :data:`STATS_DETAIL_PATHS`."""
        stats = without_details("stats") if summary else "stats"
        rows = self._read(
            f'SELECT id, kind, "order", {stats} AS stats, dataset_id, job_id, active, created_at '
            "FROM models ORDER BY id DESC LIMIT ? OFFSET ?",
            (limit, offset),
        )
        return [self._model(r, with_artifact=False) for r in rows]

    def active_model(self, *, with_artifact: bool = True) -> ModelRecord | None:
        columns = "*" if with_artifact else _MODEL_META
        rows = self._read(f"SELECT {columns} FROM models WHERE active = 1")
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
