"""The event log: every state change of the store, and events the daemon adds (faults, for instance)."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from typing import Any

from comp_daemon.service.store.base import StoreBase
from comp_daemon.service.store.records import EventRecord, record_of

__all__ = ["EventStore"]


class EventStore(StoreBase):
    """The ``events`` table (written by every change through ``_event``; read and pruned here)."""

    @staticmethod
    def _event_record(row: sqlite3.Row) -> EventRecord:
        return record_of(EventRecord, row, message=json.loads(row["message"]))

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
        with self._tx() as conn:
            n = conn.execute("DELETE FROM events WHERE time < ?", (cutoff,)).rowcount
        return int(n)
