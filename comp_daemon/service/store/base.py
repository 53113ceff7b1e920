"""The store's connection and plumbing: transactions that log events, reads, migrations, one-row fetches.

The tables' operations are in the modules beside this one, each a subclass of :class:`StoreBase`;
:class:`comp_daemon.service.store.Store` puts them together.
"""

from __future__ import annotations

import errno
import math
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal, Self

from comp_daemon.common.logs import get_logger
from comp_daemon.service.store.records import (
    EventListener,
    EventRecord,
    NotFoundError,
    StoreDamagedError,
    StoreError,
    StoreFullError,
    dumps,
)
from comp_daemon.service.store.schema import MIGRATIONS, SCHEMA_VERSION

__all__ = ["StoreBase", "check_rows", "disk_full_error", "free_bytes", "one_line"]

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


def free_bytes(path: Path) -> int | None:
    """Bytes an unprivileged writer may still use on the disk that holds ``path`` (None if unknown)."""
    folder = path if path.is_dir() else path.parent
    try:
        st = os.statvfs(folder)
    except OSError:
        return None
    return int(st.f_bavail * st.f_frsize)


#: less free space than this on the store's disk and the store says it cannot write (write_problem)
MIN_FREE_BYTES = 1 << 20
#: the trial write of write_problem: its size, and how often at most it runs
PROBE_BYTES = 64 * 1024
PROBE_INTERVAL_S = 1.0

#: SQLite's primary result codes that mean "the file could not be written": full, or an I/O error
#: (SQLite reports some ENOSPC failures, e.g. growing the -shm file, as I/O errors)
_SQLITE_FULL = 13
_SQLITE_IOERR = 10
_SQLITE_DAMAGED = frozenset({11, 26})  # SQLITE_CORRUPT, SQLITE_NOTADB


def disk_full_error(exc: BaseException, path: Path) -> StoreFullError | None:
    """``exc`` as a :class:`StoreFullError` naming ``path`` if it means the disk is full; else None."""
    if isinstance(exc, StoreFullError):
        return exc
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return StoreFullError(path, free_bytes(path))
    code = getattr(exc, "sqlite_errorcode", None)
    if not isinstance(exc, sqlite3.Error) or code is None:
        return None
    free = free_bytes(path)
    if code & 0xFF == _SQLITE_FULL or (code & 0xFF == _SQLITE_IOERR and free == 0):
        return StoreFullError(path, free)
    return None


def check_rows(rows: Sequence[object]) -> list[str]:
    """The problems in the rows of ``PRAGMA quick_check`` / ``integrity_check``: one per line of text."""
    lines = [line.strip() for row in rows for line in str(row).splitlines()]
    found = [line for line in lines if line and not line.startswith("*** in database")]
    return [] if found == ["ok"] else found


def one_line(problems: Sequence[str], first: int = 3) -> str:
    """The first ``first`` problems on one line, and how many more there are."""
    more = len(problems) - first
    return "; ".join(problems[:first]) + (f" (and {more} more)" if more > 0 else "")


class StoreBase:
    """The SQLite connection. Open with ``Store(path)``; close with :meth:`close` (or use ``with``)."""

    def __init__(
        self,
        path: str | Path,
        *,
        synchronous: Literal["full", "normal"] = "full",
        busy_timeout_ms: int = 5000,
        clock: Callable[[], float] = time.time,
        check: bool = False,
    ) -> None:
        """Open (or create) the store at ``path``.

        ``check``: run ``PRAGMA quick_check`` before anything is written, and refuse a damaged file
        with :class:`StoreDamagedError`. Whatever the check, a file SQLite cannot read as a database
        is refused with that error, a full disk with :class:`StoreFullError`, any other failure to
        open with :class:`StoreError` — each naming the file.
        """
        self.path = Path(path)
        self._clock = clock
        self._lock = threading.RLock()
        self._full: StoreFullError | None = None  # the last write failed for space, none since worked
        self._probed_at = -math.inf  # monotonic s of the last trial write (write_problem)
        self._listeners: list[EventListener] = []
        self._pending: list[EventRecord] = []
        try:
            if str(path) != ":memory:":
                _create_private(self.path)
            self._conn = sqlite3.connect(
                str(path), isolation_level=None, check_same_thread=False, timeout=busy_timeout_ms / 1000
            )
        except (OSError, sqlite3.Error) as exc:
            raise self._open_error(exc) from exc
        try:
            self._conn.row_factory = sqlite3.Row
            if check:
                problems = self.quick_check()
                if problems:
                    raise StoreDamagedError(f"store {self.path} is damaged: {one_line(problems)}")
            mode = self._conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(path) != ":memory:" and str(mode).lower() != "wal":
                raise StoreError(f"cannot put {self.path} in WAL mode (got {mode})")
            self._conn.execute("PRAGMA foreign_keys=ON")
            self._conn.execute(f"PRAGMA synchronous={'FULL' if synchronous == 'full' else 'NORMAL'}")
            self._conn.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
            self._migrate()
        except BaseException as exc:
            self._conn.close()
            if isinstance(exc, OSError | sqlite3.Error):
                raise self._open_error(exc) from exc
            raise

    def _open_error(self, exc: OSError | sqlite3.Error) -> StoreError:
        full = disk_full_error(exc, self.path)
        if full is not None:
            return full
        if getattr(exc, "sqlite_errorcode", 0) & 0xFF in _SQLITE_DAMAGED:
            return StoreDamagedError(f"store {self.path} is damaged: {exc}")
        return StoreError(f"cannot open the store {self.path}: {exc}")

    def quick_check(self) -> list[str]:
        """SQLite's ``PRAGMA quick_check``: the problems it finds (empty if the file is sound).

        It reads every page of the file (O(size)); a file SQLite cannot read at all is one problem."""
        try:
            rows = self._read("PRAGMA quick_check")
        except sqlite3.DatabaseError as exc:
            return [str(exc)]
        return check_rows([r[0] for r in rows])

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
        """One ``BEGIN IMMEDIATE`` … ``COMMIT``; rolled back whole on any error.

        A full disk is raised as :class:`StoreFullError` (the cause chained); SQLite may already
        have rolled the transaction back itself (a failed ``COMMIT``), so the rollback here is only
        issued while a transaction is open and can never hide the error that caused it.
        """
        with self._lock:
            self._pending = []
            try:
                self._conn.execute("BEGIN IMMEDIATE")
                try:
                    yield self._conn
                    self._conn.execute("COMMIT")
                except BaseException:
                    self._pending = []
                    self._rollback()
                    raise
            except (OSError, sqlite3.Error) as exc:
                full = disk_full_error(exc, self.path)
                if full is None:
                    raise
                self._full = full
                raise full from exc
            except StoreFullError as exc:
                self._full = exc
                raise
            events, self._pending = self._pending, []
            listeners = list(self._listeners)
        self._notify(listeners, events)

    def write_problem(self) -> str | None:
        """Why the store cannot write now, in one sentence starting "store not writable"; None if it can.

        Not writable: less than :data:`MIN_FREE_BYTES` free on the store's disk, or a write failed
        for a full disk and no trial write has worked since. A trial write (a :data:`PROBE_BYTES`
        row inserted and rolled back: the pages it needs are allocated, nothing is kept) runs at most
        every :data:`PROBE_INTERVAL_S` while so, so the store says it can write again within that
        time once room was made. A small write that still fits (a job marked failed) does not count:
        the next data set or model may not.
        """
        free = free_bytes(self.path)
        if free is not None and free < MIN_FREE_BYTES and str(self.path) != ":memory:":
            return (
                f"store not writable: only {free} bytes free on the disk of {self.path}; "
                "free space on that disk"
            )
        with self._lock:
            full = self._full
            if full is None:
                return None
            now = time.monotonic()
            if now - self._probed_at >= PROBE_INTERVAL_S:
                self._probed_at = now
                full = self._trial_write()
                self._full = full
        return None if full is None else f"store not writable: {full}"

    def _trial_write(self) -> StoreFullError | None:
        """Insert a :data:`PROBE_BYTES` event and roll it back; the full-disk error it met, if any."""
        conn = self._conn
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                conn.execute(
                    "INSERT INTO events (time, kind, message) VALUES (?, 'store.probe', ?)",
                    (self._clock(), "x" * PROBE_BYTES),
                )
            finally:
                self._rollback()
        except (OSError, sqlite3.Error) as exc:
            full = disk_full_error(exc, self.path)
            if full is None:
                raise
            return full
        return None

    def _rollback(self) -> None:
        if not self._conn.in_transaction:
            return  # SQLite ended it already (e.g. a COMMIT that failed on a full disk)
        try:
            self._conn.execute("ROLLBACK")
        except sqlite3.Error:  # the error being raised is the one that matters
            _log.exception("store: rollback failed", path=str(self.path))

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
                with self._tx() as conn:
                    sql = "SELECT 1 FROM schema_version WHERE version = ?"
                    done = conn.execute(sql, (version,)).fetchone()
                    if done is None:
                        for statement in statements:
                            conn.execute(statement)
                        conn.execute(
                            "INSERT INTO schema_version (version, applied_at) VALUES (?, ?)",
                            (version, self._clock()),
                        )
            newest = self._conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
            if newest is not None and newest > SCHEMA_VERSION:
                raise StoreError(
                    f"{self.path} has schema version {newest}, newer than this program's {SCHEMA_VERSION}"
                )

    def schema_version(self) -> int:
        row = self._read("SELECT MAX(version) AS v FROM schema_version")[0]
        return int(row["v"] or 0)
