"""The SQLite store: migrations, the target lifecycle, idempotent batches, recovery, kill -9."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from comp_daemon.service.store import (
    SCHEMA_VERSION,
    TARGET_ACTIVE_STATES,
    TARGET_STATES,
    BatchRecord,
    ConflictError,
    EventRecord,
    IdempotencyConflict,
    ModelDraft,
    NotFoundError,
    Store,
)
from comp_daemon.service.store.records import record_of

AXES = {"a1": 0.0, "a2": -90.0, "a3": 90.0, "a4": 0.0, "a5": 45.0, "a6": 0.0}


def _targets(n: int, tag: str = "p") -> list[dict[str, object]]:
    return [{**AXES, "a1": float(i), "pose_id": f"{tag}{i}"} for i in range(n)]


def _sha(obj: object) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    s = Store(tmp_path / "db" / "store.sqlite3")
    yield s
    s.close()


def test_open_applies_migrations_once(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite3"
    Store(path).close()
    Store(path).close()  # a second open changes nothing
    conn = sqlite3.connect(path)
    versions = [r[0] for r in conn.execute("SELECT version FROM schema_version ORDER BY version")]
    assert versions == list(range(1, SCHEMA_VERSION + 1))
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"datasets", "models", "jobs", "targets", "batches", "events", "schema_version"} <= tables
    conn.close()


def test_a_new_data_folder_and_database_are_private_under_umask_022(tmp_path: Path) -> None:
    data = tmp_path / "data"
    old = os.umask(0o022)
    try:
        with Store(data / "store.sqlite3") as s:
            s.submit_batch("k", _sha(_targets(2)), _targets(2))  # a write: the -wal and -shm files exist
            modes = {p.name: p.stat().st_mode & 0o777 for p in data.iterdir()}
            folder = data.stat().st_mode & 0o777
    finally:
        os.umask(old)
    assert folder == 0o700
    assert modes == {"store.sqlite3": 0o600, "store.sqlite3-wal": 0o600, "store.sqlite3-shm": 0o600}


def test_a_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite3"
    Store(path).close()
    conn = sqlite3.connect(path)
    conn.execute("INSERT INTO schema_version VALUES (?, 0)", (SCHEMA_VERSION + 1,))
    conn.commit()
    conn.close()
    with pytest.raises(Exception, match="newer than this program"):
        Store(path)


def test_foreign_keys_are_enforced(store: Store) -> None:
    with pytest.raises(NotFoundError):
        store.create_job("fit", {}, dataset_id=999)
    with pytest.raises(sqlite3.IntegrityError):
        store._conn.execute(
            "INSERT INTO targets (batch_id, idempotency_key, seq, queue_pos, request, state, created_at,"
            " updated_at) VALUES (999, 'x', 1, 1, '{}', 'queued', 0, 0)"
        )


def test_target_lifecycle_and_refused_moves(store: Store) -> None:
    _, targets, created = store.submit_batch("k1", _sha(1), _targets(3))
    assert created and [t.state for t in targets] == ["queued"] * 3 and [t.seq for t in targets] == [1, 2, 3]
    first = store.claim_next_target()
    assert first is not None and first.id == targets[0].id and first.state == "compensating"
    assert first.started_at is not None
    with pytest.raises(ConflictError, match="cannot become done"):
        store.advance_target(first.id, "done")
    store.advance_target(first.id, "moving", commanded_axes_deg=[1, 2, 3, 4, 5, 6])
    store.advance_target(first.id, "settling")
    done = store.advance_target(
        first.id, "done", final_joint_errors_deg={"1": 0.0004, "2": -0.0002, "4": None}
    )
    assert done.state == "done" and done.finished_at is not None
    assert done.commanded_axes_deg == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert done.final_joint_errors_deg == {"1": 0.0004, "2": -0.0002, "4": None}
    with pytest.raises(ConflictError, match="only queued or interrupted"):
        store.cancel_target(first.id)
    cancelled = store.cancel_target(targets[2].id, by="op")
    assert cancelled.state == "cancelled" and "op" in (cancelled.reason or "")
    second = store.claim_next_target()
    assert second is not None and second.id == targets[1].id
    failed = store.advance_target(second.id, "failed", reason="unreachable: outside the workspace")
    assert failed.reason == "unreachable: outside the workspace"
    assert store.claim_next_target() is None
    with pytest.raises(ValueError, match="finite"):
        store.advance_target(second.id, "done", commanded_axes_deg=[float("nan")] * 6)
    kinds = [e.kind for e in store.list_events(target_id=first.id)]
    assert kinds == ["target.compensating", "target.moving", "target.settling", "target.done"]


def test_idempotent_batches(store: Store) -> None:
    body = _targets(4)
    b1, t1, created1 = store.submit_batch("mes-42", _sha(body), body)
    b2, t2, created2 = store.submit_batch("mes-42", _sha(body), body)
    assert created1 and not created2
    assert b1 == b2 and [t.id for t in t1] == [t.id for t in t2]
    with pytest.raises(IdempotencyConflict):
        store.submit_batch("mes-42", _sha(_targets(5)), _targets(5))
    assert len(store.list_targets()) == 4


def test_a_failing_batch_stores_nothing(store: Store) -> None:
    bad = [*_targets(3), {"a1": float("nan")}]  # not JSON: the insert of the 4th target fails
    with pytest.raises(ValueError):
        store.submit_batch("k", "h", bad)
    assert store.list_targets() == [] and store.find_batch("k") is None
    assert store.list_events() == []


def test_listeners_hear_only_committed_events(store: Store) -> None:
    heard: list[EventRecord] = []
    store.add_listener(heard.append)
    with pytest.raises(ValueError):
        store.submit_batch("k", "h", [{"a1": float("inf")}])
    assert heard == []
    store.submit_batch("k", "h", _targets(2))
    assert [e.kind for e in heard] == ["batch.accepted"]
    assert heard[0].id == store.list_events()[-1].id


def test_restart_recovery(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite3"
    with Store(path) as s:
        _, targets, _ = s.submit_batch("b1", "h1", _targets(5))
        moving = s.claim_next_target()
        assert moving is not None
        s.advance_target(moving.id, "moving", commanded_axes_deg=[0, -90, 90, 0, 45, 0])
        job = s.create_job("fit", {"model": "kinematic"})
        s.start_job(job.id)
    with Store(path) as s:  # as after a restart
        report = s.recover()
        assert report.interrupted_targets == [moving.id]
        assert report.queued_targets == 4
        assert report.failed_jobs == [job.id]
        interrupted = s.get_target(moving.id)
        assert interrupted.state == "interrupted" and "restart" in (interrupted.reason or "")
        assert interrupted.commanded_axes_deg == [0, -90, 90, 0, 45, 0]
        queued = s.list_targets(states=["queued"])
        assert [t.id for t in queued] == [t.id for t in targets[1:]]  # in order, intact
        assert [t.request for t in queued] == [t.request for t in targets[1:]]
        # the loop goes on with the next queued target, never silently redoing the interrupted one
        nxt = s.claim_next_target()
        assert nxt is not None and nxt.id == targets[1].id
        assert s.get_job(job.id).state == "failed"
        # the operator may requeue it: it goes to the end of the queue
        again = s.requeue_target(moving.id, by="op")
        assert again.state == "queued" and again.commanded_axes_deg is None
        assert [t.id for t in s.list_targets(states=["queued"])][-1] == moving.id
        assert s.recover().interrupted_targets == [nxt.id]  # a second recovery: idempotent


def test_jobs_models_and_activation(store: Store) -> None:
    ds = store.add_dataset(name="c", format="csv", content="a1\n", sha256="0" * 64, rows=1, summary={})
    job = store.create_job("fit", {"model": "kinematic"}, dataset_id=ds.id, max_pending=1)
    with pytest.raises(ConflictError, match="max_pending"):
        store.create_job("fit", {}, dataset_id=ds.id, max_pending=1)
    with pytest.raises(ConflictError, match="used by unfinished"):
        store.delete_dataset(ds.id)
    store.start_job(job.id)
    assert store.set_job_progress(job.id, 0.5, "half")
    draft = ModelDraft(kind="kinematic", order=None, artifact={"a": 1}, stats={"s": 2}, dataset_id=ds.id)
    done, model = store.finish_job(job.id, {"ok": True}, model=draft)
    assert done.state == "done" and done.progress == 1.0 and model is not None and model.job_id == job.id
    assert not store.set_job_progress(job.id, 0.7)
    with pytest.raises(ConflictError):
        store.finish_job(job.id, {})
    other = store.add_model(ModelDraft(kind="chebyshev", order=3, artifact={}, stats={}, dataset_id=None))
    store.activate_model(model.id)
    store.activate_model(other.id)
    active = store.active_model()
    assert active is not None and active.id == other.id and active.artifact == {}
    assert [m.active for m in store.list_models()] == [True, False]
    store.delete_dataset(ds.id)
    assert store.get_model(model.id, with_artifact=True).dataset_id is None
    assert store.get_model(model.id, with_artifact=True).artifact == {"a": 1}


WRITER = textwrap.dedent(
    """
    import sys
    from comp_daemon.service.store import Store

    store = Store(sys.argv[1], synchronous="normal")
    n = 0
    while True:
        key = f"mes-{n}"
        axes = {"a2": -90.0, "a3": 90.0, "a4": 0.0, "a5": 45.0, "a6": 0.0}
        targets = [{"a1": float(i), **axes, "pose_id": f"{n}.{i}"} for i in range(5)]
        _, stored, _ = store.submit_batch(key, f"hash-{n}", targets)
        print("accepted", key, ",".join(str(t.id) for t in stored), flush=True)
        t = store.claim_next_target()  # the daemon's side: one target further per batch
        store.advance_target(t.id, "moving")
        print("moving", t.id, flush=True)
        if n % 2:
            store.advance_target(t.id, "settling")
            store.advance_target(t.id, "done", final_joint_errors_deg={"1": 0.0})
            print("done", t.id, flush=True)
        n += 1
    """
)


def test_kill_9_mid_batch_loses_and_repeats_nothing(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite3"
    script = tmp_path / "writer.py"
    script.write_text(WRITER, encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script), str(path)], stdout=subprocess.PIPE, text=True)
    accepted: dict[str, list[int]] = {}
    moving: set[int] = set()
    done: set[int] = set()

    def note(line: str) -> None:
        word, *rest = line.split()
        if word == "accepted":
            accepted[rest[0]] = [int(x) for x in rest[1].split(",")]
        elif word == "moving":
            moving.add(int(rest[0]))
        elif word == "done":
            done.add(int(rest[0]))

    assert proc.stdout is not None
    deadline = time.monotonic() + 60
    while len(accepted) < 40 and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        note(line)
    os.kill(proc.pid, signal.SIGKILL)  # mid-batch: it is writing the next one
    proc.wait(timeout=10)
    for line in proc.stdout.read().splitlines():  # reported before it died, not read yet (whole lines:
        note(line)  # each is one write, shorter than PIPE_BUF)
    proc.stdout.close()
    assert len(accepted) >= 40, "the writer did not get going"

    with Store(path) as store:
        report = store.recover()
        batches = store._conn.execute("SELECT idempotency_key FROM batches").fetchall()
        keys = {r[0] for r in batches}
        targets = store.list_targets(limit=100_000)
        # every accepted batch is there, whole, with the ids it was given
        for key, ids in accepted.items():
            batch = store.find_batch(key)
            assert batch is not None
            _, stored = store.get_batch(batch.id)
            assert [t.id for t in stored] == ids
        # at most the one batch in flight committed without being reported; nothing else, and whole
        assert set(accepted) <= keys and len(keys - set(accepted)) <= 1
        assert len(targets) == 5 * len(keys)
        assert len({t.idempotency_key for t in targets}) == len(targets)
        # each target in exactly one state, none left active; reported-moving ones not done are interrupted
        by_id = {t.id: t for t in targets}
        assert all(t.state in TARGET_STATES and t.state not in TARGET_ACTIVE_STATES for t in targets)
        for target_id in moving - done:
            assert by_id[target_id].state in ("interrupted", "done"), by_id[target_id]
        for target_id in done:
            assert by_id[target_id].state == "done"
        assert set(report.interrupted_targets) <= moving | {t.id for t in targets if t.state == "interrupted"}
        # the MES retries every batch it sent (it cannot know which ones arrived): nothing is repeated
        n_before = len(targets)
        for n in range(len(accepted) + 1):
            key = f"mes-{n}"
            body = [
                {
                    "a1": float(i),
                    "a2": -90.0,
                    "a3": 90.0,
                    "a4": 0.0,
                    "a5": 45.0,
                    "a6": 0.0,
                    "pose_id": f"{n}.{i}",
                }
                for i in range(5)
            ]
            _, stored, created = store.submit_batch(key, f"hash-{n}", body)
            assert created == (key not in keys)
            assert [t.request["pose_id"] for t in stored] == [f"{n}.{i}" for i in range(5)]
        assert len(store.list_targets(limit=100_000)) == n_before + 5 * (len(accepted) + 1 - len(keys))


def test_record_of_takes_each_field_from_its_column_unless_decoded() -> None:
    conn = sqlite3.connect(":memory:")
    conn.row_factory = sqlite3.Row
    row = conn.execute(
        "SELECT 7 AS id, 'k' AS idempotency_key, 'ab' AS request_sha256, NULL AS source, 3 AS size, "
        "1.5 AS created_at, 'extra' AS unused"
    ).fetchone()
    assert record_of(BatchRecord, row) == BatchRecord(7, "k", "ab", None, 3, 1.5)
    assert record_of(BatchRecord, row, size=4, source="mes").size == 4
    meta = conn.execute("SELECT 1 AS id, 'kinematic' AS kind").fetchone()
    with pytest.raises(IndexError):  # a field neither read nor decoded is a mistake, not a None
        record_of(BatchRecord, meta)
