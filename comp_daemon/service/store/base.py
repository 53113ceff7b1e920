"""The store's connection and plumbing: transactions that log events, reads, migrations, one-row fetches.

The tables' operations are in the modules beside this one, each a subclass of :class:`StoreBase`;
:class:`comp_daemon.service.store.Store` puts them together.
"""

from __future__ import annotations

import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal, Self

from comp_daemon.common.logs import get_logger
from comp_daemon.service.store.records import EventListener, EventRecord, NotFoundError, StoreError, dumps
from comp_daemon.service.store.schema import MIGRATIONS, SCHEMA_VERSION

__all__ = ["StoreBase"]

_log = get_logger("comp_daemon.store")

#: the table of each kind of thing :meth:`StoreBase._fetch` looks up by id
_TABLES: dict[str, str] = {
    "dataset": "datasets",
    "job": "jobs",
    "model": "models",
    "batch": "batches",
    "target": "targets",
}


def _create_private(path: Path) -> None:
    """Make the database's folder ``0700`` and the database file ``0600`` if they are new, whatever the umask.

    ``mkdir``'s and SQLite's own create modes are masked by the process's umask (the file would be
    ``0644`` under the usual ``022``); SQLite gives the ``-wal`` and ``-shm`` files the database
    file's mode, so creating that one ``0600`` covers all three. A folder or a database that exists
    keeps its mode (under systemd the unit's ``StateDirectoryMode=`` sets the folder's).
    """
    folder = path.parent
    if not folder.exists():
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(folder, 0o700)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    except FileExistsError:
        return
    os.close(fd)


class StoreBase:
    """The SQLite connection. Open with ``Store(path)``; close with :meth:`close` (or use ``with``)."""

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
            _create_private(self.path)
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

    def __enter__(self) -> Self:
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
        self._notify(listeners, events)

    @staticmethod
    def _notify(listeners: Sequence[EventListener], events: Sequence[EventRecord]) -> None:
        """Tell ``listeners`` about committed ``events``, outside the lock."""
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
            (now, kind, target_id, job_id, dumps(dict(message))),
        )
        assert cur.lastrowid is not None
        self._pending.append(EventRecord(cur.lastrowid, now, kind, target_id, job_id, dict(message)))

    def _read(self, sql: str, args: Sequence[Any] = ()) -> list[sqlite3.Row]:
        with self._lock:
            return self._conn.execute(sql, tuple(args)).fetchall()

    @staticmethod
    def _fetch(conn: sqlite3.Connection, what: str, ident: int, columns: str = "*") -> sqlite3.Row:
        """The row of ``what`` (dataset, job, model, batch, target) with id ``ident``; else NotFoundError."""
        row = conn.execute(f"SELECT {columns} FROM {_TABLES[what]} WHERE id = ?", (ident,)).fetchone()
        if row is None:
            raise NotFoundError(what, ident)
        return row

    def _migrate(self) -> None:
        with self._lock:
            self._conn.execute(
                "CREATE TABLE IF NOT EXISTS schema_version"
                " (version INTEGER PRIMARY KEY, applied_at REAL NOT NULL)"
            )
            for version, statements in MIGRATIONS:
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
