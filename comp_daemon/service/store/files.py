"""The files beside the store's database: the marker that says a store exists, the rotated online
backups, the restore, and the lock the running daemon holds.

Why a marker. SQLite takes a missing or zero-length file for a new, empty database. After a crash,
a full disk or an operator's mistake that is how a store with years of data sets, models and
targets would silently start again empty. The first time a store is created (or an existing one is
opened without it) ``<db>.marker`` is written beside the database; from then on a missing or empty
database with the marker, or with backups in the backup folder, is refused with one line that says
how to recover. Starting empty on purpose means moving the database, the marker and the backups
away (or ``comp-daemon store restore`` of a backup).

Backups (:func:`make_backup`) use SQLite's online backup API on a read-only connection of their
own: they run while the daemon works (WAL readers never block its writers), are checked with
``PRAGMA quick_check`` before they count, are written under a temporary name and renamed, and only
the newest ``keep`` are kept. :func:`restore` puts a checked backup in place of the database, after
moving the current database files into a ``replaced-<time>`` folder (nothing is deleted).
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from comp_daemon.common.atomic import write_json_atomic
from comp_daemon.service.store.base import check_rows, disk_full_error, one_line
from comp_daemon.service.store.records import StoreDamagedError, StoreError

__all__ = [
    "Backup",
    "StoreLock",
    "check_file",
    "existed_before",
    "list_backups",
    "make_backup",
    "marker_path",
    "refuse_if_lost",
    "restore",
    "write_marker",
]

_SIDE_FILES = ("-wal", "-shm", "-journal")


def marker_path(db_path: Path) -> Path:
    return db_path.with_name(db_path.name + ".marker")


def _stamp(t: float) -> str:
    """UTC time as ``YYYYmmddTHHMMSS.mmmZ``: file names that sort in time order."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime(t)) + f".{int(t * 1000) % 1000:03d}Z"


@dataclass(frozen=True, slots=True)
class Backup:
    path: Path
    size_bytes: int
    created_at: float  # UNIX seconds (the file's modification time)


def list_backups(backup_dir: Path, db_path: Path) -> list[Backup]:
    """The backups of ``db_path`` in ``backup_dir``, oldest first."""
    if not backup_dir.is_dir():
        return []
    found = []
    for p in sorted(backup_dir.glob(f"{db_path.name}.*.backup")):
        st = p.stat()
        found.append(Backup(p, st.st_size, st.st_mtime))
    return found


def existed_before(db_path: Path, backup_dir: Path) -> str | None:
    """What shows that a store existed at ``db_path`` (its marker, its backups); None if nothing."""
    evidence = []
    marker = marker_path(db_path)
    if marker.exists():
        try:
            created = json.loads(marker.read_text(encoding="utf-8")).get("created_at_utc", "?")
        except (OSError, ValueError, AttributeError):
            created = "?"
        evidence.append(f"marker {marker} from {created}")
    backups = list_backups(backup_dir, db_path)
    if backups:
        evidence.append(f"{len(backups)} backup(s) in {backup_dir}")
    return ", ".join(evidence) or None


def recovery_hint(db_path: Path, backup_dir: Path) -> str:
    backups = list_backups(backup_dir, db_path)
    if backups:
        newest = backups[-1]
        when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(newest.created_at))
        return (
            "to recover, with the daemon stopped: `comp-daemon store restore --config FILE` "
            f"(the newest backup, {newest.path.name}, {when})"
        )
    return (
        f"no backup in {backup_dir}: recover {db_path} from the machine's own backups, or move "
        f"{db_path.name}* away to start with an empty store"
    )


def refuse_if_lost(db_path: Path, backup_dir: Path) -> None:
    """:class:`StoreDamagedError` if the database is missing or empty although a store existed."""
    try:
        size = db_path.stat().st_size
    except FileNotFoundError:
        size = None
    if size:
        return
    evidence = existed_before(db_path, backup_dir)
    if evidence is None:
        return
    what = "missing" if size is None else "empty (0 bytes)"
    raise StoreDamagedError(
        f"store {db_path} is {what} but a store existed there ({evidence}); nothing was changed; "
        + recovery_hint(db_path, backup_dir)
    )


def write_marker(db_path: Path) -> None:
    """Write the marker beside the database if it is not there yet."""
    marker = marker_path(db_path)
    if marker.exists():
        return
    now = time.time()
    doc = {
        "what": "a comp-daemon store exists here; an empty or missing database beside it is refused",
        "database": db_path.name,
        "created_at_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now)),
    }
    try:
        write_json_atomic(marker, doc)
    except OSError as exc:
        full = disk_full_error(exc, marker)
        raise (full or StoreError(f"cannot write {marker}: {exc}")) from exc


def check_file(path: Path, *, full: bool = False) -> list[str]:
    """The problems SQLite finds in the database file ``path`` (``quick_check``, or with ``full``
    the slower ``integrity_check``), read-only; empty if it is sound."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        return [f"cannot read {path}: {exc.strerror}"]
    if size == 0:
        return [f"{path} is empty (0 bytes)"]
    try:
        conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        return [f"cannot open {path}: {exc}"]
    try:
        rows = conn.execute(f"PRAGMA {'integrity_check' if full else 'quick_check'}").fetchall()
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.Error as exc:
        return [str(exc)]
    finally:
        conn.close()
    problems = check_rows([r[0] for r in rows])
    if not problems and "schema_version" not in tables:
        problems.append(f"{path} is an SQLite file but not a comp-daemon store")
    return problems


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_backup(db_path: Path, backup_dir: Path, *, keep: int) -> Backup:
    """Copy the live store into ``backup_dir`` (online; see the module docstring); keep the newest ``keep``.

    A full disk is :class:`~comp_daemon.service.store.StoreFullError` naming the backup folder (the
    partial copy is removed); a copy that fails its check is removed and refused."""
    if not db_path.is_file() or db_path.stat().st_size == 0:
        raise StoreError(f"no store to back up at {db_path}")
    backup_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    dest = backup_dir / f"{db_path.name}.{_stamp(time.time())}.backup"
    part = dest.with_name(dest.name + ".part")
    try:
        src = sqlite3.connect(f"{db_path.resolve().as_uri()}?mode=ro", uri=True)
        try:
            dst = sqlite3.connect(part)
            try:
                src.backup(dst)
                dst.execute("PRAGMA journal_mode=DELETE")  # a single self-contained file
            finally:
                dst.close()
        finally:
            src.close()
        os.chmod(part, 0o600)  # the store's data, private whatever the umask of the caller
        with open(part, "rb+") as fh:
            os.fsync(fh.fileno())
        problems = check_file(part)
        if problems:
            raise StoreError(f"the backup of {db_path} failed its check: {one_line(problems)}")
        os.replace(part, dest)
        _fsync_dir(backup_dir)
    except (OSError, sqlite3.Error) as exc:
        part.unlink(missing_ok=True)
        full = disk_full_error(exc, backup_dir)
        raise (full or StoreError(f"backup of {db_path} to {backup_dir} failed: {exc}")) from exc
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    for old in list_backups(backup_dir, db_path)[:-keep]:
        old.path.unlink(missing_ok=True)
    st = dest.stat()
    return Backup(dest, st.st_size, st.st_mtime)


class StoreLock:
    """An exclusive ``flock`` on ``<db>.lock`` while one process (the daemon, a restore) owns the store."""

    def __init__(self, db_path: Path) -> None:
        self.path = db_path.with_name(db_path.name + ".lock")
        self._fh: IO[str] | None = None

    def acquire(self) -> StoreLock:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        fh = open(fd, "r+", encoding="utf-8")  # held until release()
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "?"
            fh.close()
            raise StoreError(
                f"the store {self.path.with_suffix('')} is in use by process {holder} (a running "
                "comp-daemon); stop it first (systemctl stop comp-daemon)"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"{os.getpid()}\n")
        fh.flush()
        self._fh = fh
        return self

    def release(self) -> None:
        if self._fh is not None:
            self._fh.close()  # closing drops the flock
            self._fh = None

    def __enter__(self) -> StoreLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def restore(db_path: Path, backup_dir: Path, backup: Path | None = None) -> tuple[Backup, Path | None]:
    """Put ``backup`` (default: the newest) in place of the store; the daemon must be stopped.

    Returns the backup used and the folder the replaced database files were moved to (None if
    there were none). The backup is checked first; nothing is deleted."""
    backups = list_backups(backup_dir, db_path)
    if backup is None:
        if not backups:
            raise StoreError(f"no backup of {db_path.name} in {backup_dir}")
        chosen = backups[-1]
    else:
        if not backup.is_file():
            raise StoreError(f"no backup file {backup}")
        st = backup.stat()
        chosen = Backup(backup, st.st_size, st.st_mtime)
    problems = check_file(chosen.path)
    if problems:
        raise StoreDamagedError(f"backup {chosen.path} is damaged: {one_line(problems)}; pick another")
    with StoreLock(db_path):
        present = [p for p in [db_path, *(Path(f"{db_path}{s}") for s in _SIDE_FILES)] if p.exists()]
        aside: Path | None = None
        if present:
            aside = db_path.parent / f"replaced-{_stamp(time.time())}"
            aside.mkdir(mode=0o700)
            for p in present:
                os.replace(p, aside / p.name)
        part = db_path.with_name(db_path.name + ".restore.part")
        try:
            shutil.copyfile(chosen.path, part)
            os.chmod(part, 0o600)
            with open(part, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(part, db_path)
            _fsync_dir(db_path.parent)
        except OSError as exc:
            part.unlink(missing_ok=True)
            full = disk_full_error(exc, db_path)
            kept = f"; the replaced files are in {aside}" if aside is not None else ""
            raise (full or StoreError(f"restoring {chosen.path} to {db_path} failed: {exc}{kept}")) from exc
        write_marker(db_path)
    return chosen, aside
