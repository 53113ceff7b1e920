"""``comp-daemon store check|backup|restore``: look after the daemon's SQLite store.

- ``check``: is the database sound (``PRAGMA quick_check``, ``--full`` for ``integrity_check``),
  and is it missing or empty where a store existed (its marker, its backups)? Prints what it holds
  and the backups; exit 0 if sound, 3 if not (the daemon refuses such a store at start).
- ``backup``: one online backup now, beside the scheduled ones (it may run while the daemon
  works); the newest ``store.backup_keep`` are kept.
- ``restore``: put the newest backup (or ``--backup FILE``) in place of the database; the daemon
  must be stopped. The current database files are moved to ``<data_dir>/replaced-<time>/``.

The store is the one of ``--config FILE`` (``[store]``), or ``--data-dir DIR`` for a daemon run
without a file (the quick start keeps its data in ``./var/sim``). See docs/daemon.md, "The store".
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import sys
import time
from pathlib import Path
from typing import Any

from comp_daemon.commands.errors import UserError

#: the exit code of a store that is damaged, or missing or empty where one existed (as ``run``'s)
EXIT_STORE = 3
_COUNTED = ("datasets", "models", "jobs", "batches", "targets", "events")


def register(subparsers: argparse._SubParsersAction) -> None:
    store = subparsers.add_parser("store", help="the daemon's store: check it, back it up, restore a backup")
    sub = store.add_subparsers(dest="store_command", metavar="STORE_COMMAND", required=True)

    def add(name: str, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        where = p.add_mutually_exclusive_group(required=True)
        where.add_argument("--config", metavar="FILE", help="the daemon's configuration file ([store])")
        where.add_argument(
            "--data-dir", metavar="DIR", help="the store's folder, for a daemon run without a file"
        )
        return p

    check = add("check", "check the store: sound, or damaged, missing or empty where one existed")
    check.add_argument("--full", action="store_true", help="PRAGMA integrity_check (slower, more thorough)")
    check.set_defaults(func=_check)
    backup = add("backup", "make one online backup now (the daemon may be running)")
    backup.set_defaults(func=_backup)
    restore = add("restore", "replace the store by a backup (the daemon must be stopped)")
    restore.add_argument(
        "--backup", metavar="FILE", default=None, help="the backup to restore (default: the newest)"
    )
    restore.set_defaults(func=_restore)


def _paths(args: argparse.Namespace) -> tuple[Path, Path, int]:
    """The database, the backup folder and how many backups to keep."""
    from pydantic import ValidationError

    from comp_daemon.service.config import load_settings

    try:
        if args.config is not None:
            settings = load_settings(args.config)
        else:
            settings = load_settings(None, store={"data_dir": Path(args.data_dir).resolve()})
    except ValidationError as exc:
        raise UserError(f"{args.config}: {exc}") from None
    conf = settings.store
    return conf.db_path, conf.backup_path, conf.backup_keep


def _counts(db_path: Path) -> dict[str, int]:
    conn = sqlite3.connect(f"{db_path.resolve().as_uri()}?mode=ro", uri=True)
    try:
        return {t: int(conn.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0]) for t in _COUNTED}
    finally:
        conn.close()


def _when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))


def _check(args: argparse.Namespace) -> int:
    from comp_daemon.service.store import StoreDamagedError
    from comp_daemon.service.store import files as store_files
    from comp_daemon.service.store.base import one_line

    db_path, backup_dir, _ = _paths(args)
    report: dict[str, Any] = {"database": str(db_path), "backup_dir": str(backup_dir)}
    backups = store_files.list_backups(backup_dir, db_path)
    report["backups"] = [
        {"file": b.path.name, "bytes": b.size_bytes, "created": _when(b.created_at)} for b in backups
    ]
    problems: list[str] = []
    try:
        store_files.refuse_if_lost(db_path, backup_dir)
    except StoreDamagedError as exc:
        problems.append(str(exc))
    if not problems and not db_path.exists():
        report["ok"], report["note"] = True, "no store yet: the daemon creates it at its first start"
        print(json.dumps(report, indent=2))
        return 0
    if not problems:
        started = time.perf_counter()
        found = store_files.check_file(db_path, full=args.full)
        report["check"] = "integrity_check" if args.full else "quick_check"
        report["check_s"] = round(time.perf_counter() - started, 3)
        if found:
            hint = store_files.recovery_hint(db_path, backup_dir)
            problems.append(f"store {db_path} is damaged: {one_line(found)}; {hint}")
        else:
            report["bytes"] = db_path.stat().st_size
            report["rows"] = _counts(db_path)
    report["ok"] = not problems
    if problems:
        report["problems"] = problems
    print(json.dumps(report, indent=2))
    for p in problems:
        print(f"comp-daemon store check: {p}", file=sys.stderr)
    return 0 if not problems else EXIT_STORE


def _backup(args: argparse.Namespace) -> int:
    from comp_daemon.service.store import StoreError
    from comp_daemon.service.store import files as store_files

    db_path, backup_dir, keep = _paths(args)
    started = time.perf_counter()
    try:
        backup = store_files.make_backup(db_path, backup_dir, keep=keep)
    except StoreError as exc:
        raise UserError(str(exc)) from None
    took = time.perf_counter() - started
    print(f"backed up {db_path} to {backup.path} ({backup.size_bytes} bytes, {took:.3f} s; keeping {keep})")
    return 0


def _restore(args: argparse.Namespace) -> int:
    from comp_daemon.service.store import StoreError
    from comp_daemon.service.store import files as store_files

    db_path, backup_dir, _ = _paths(args)
    chosen = None if args.backup is None else Path(args.backup)
    try:
        backup, aside = store_files.restore(db_path, backup_dir, chosen)
    except StoreError as exc:
        raise UserError(str(exc)) from None
    print(f"restored {db_path} from {backup.path} ({_when(backup.created_at)})")
    if aside is not None:
        print(f"the replaced database files are in {aside}")
    return 0
