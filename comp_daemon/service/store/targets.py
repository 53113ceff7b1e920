"""The target queue: batches accepted once per idempotency key, and each target's lifecycle."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping, Sequence
from typing import Any

from comp_daemon.service.store.base import StoreBase
from comp_daemon.service.store.records import (
    TARGET_FINAL_STATES,
    TARGET_STATES,
    TARGET_TRANSITIONS,
    BatchRecord,
    ConflictError,
    IdempotencyConflict,
    TargetRecord,
    dumps,
    finite,
    loads,
    record_of,
)

__all__ = ["TargetStore"]


class TargetStore(StoreBase):
    """The ``batches`` and ``targets`` tables (lifecycle: :mod:`comp_daemon.service.store`)."""

    @staticmethod
    def _batch(row: sqlite3.Row) -> BatchRecord:
        return record_of(BatchRecord, row)

    @staticmethod
    def _target(row: sqlite3.Row) -> TargetRecord:
        return record_of(
            TargetRecord,
            row,
            request=json.loads(row["request"]),
            commanded_axes_deg=loads(row["commanded_axes"]),
            final_joint_errors_deg=loads(row["final_joint_errors"]),
        )

    def _target_row(self, conn: sqlite3.Connection, target_id: int) -> TargetRecord:
        return self._target(self._fetch(conn, "target", target_id))

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
                    (batch_id, f"{idempotency_key}#{seq}", seq, pos + seq, dumps(dict(t)), now, now)
                    for seq, t in enumerate(targets, start=1)
                ],
            )
            batch = self._batch(self._fetch(conn, "batch", batch_id))
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
            batch = self._batch(self._fetch(self._conn, "batch", batch_id))
            return batch, self._batch_targets(self._conn, batch_id)

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
        if state not in TARGET_TRANSITIONS[target.state]:
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
        compensation: Mapping[str, Any] | None = None,
    ) -> TargetRecord:
        """Move a target along its lifecycle (the daemon's call); refused for moves not in the diagram.

        ``compensation``: how the commanded axes came about (model id, mapping, nominal solution,
        predicted residual and σ), kept in the move's event (``target.moving``) for the API."""
        if state not in TARGET_STATES:
            raise ValueError(f"unknown target state {state!r}")
        set_sql, set_args, extra = "", list[Any](), dict[str, Any]()
        if commanded_axes_deg is not None:
            axes = [finite(float(a)) for a in commanded_axes_deg]
            set_sql += ", commanded_axes = ?"
            set_args.append(dumps(axes))
            extra["commanded_axes_deg"] = axes
        if final_joint_errors_deg is not None:
            errors = {
                str(k): (None if v is None else finite(float(v))) for k, v in final_joint_errors_deg.items()
            }
            set_sql += ", final_joint_errors = ?"
            set_args.append(dumps(errors))
            extra["final_joint_errors_deg"] = errors
        if compensation is not None:
            extra["compensation"] = json.loads(dumps(dict(compensation)))
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
            self._fetch(conn, "batch", batch_id, "id")
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
