"""The store's faults in-process: SQLite's own "database or disk is full" (SQLITE_FULL, injected with
``PRAGMA max_page_count``, the same error as ENOSPC at the store's write), the marker and the
refusal of an emptied store, backups, restore and its lock, and the ``store`` commands.

The real processes on a real full disk and on damaged files are in test_e2e_store_faults.py.
"""

from __future__ import annotations

import asyncio
import json
import os
import sqlite3
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_client import in_process_service, job_done
from test_service_api import auth, campaign_csv, make_settings

from comp_daemon.cli import main as cli_main
from comp_daemon.service import jobs as jobs_module
from comp_daemon.service.api import open_store
from comp_daemon.service.store import Store, StoreDamagedError, StoreError, StoreFullError
from comp_daemon.service.store import base as store_base
from comp_daemon.service.store import files as store_files


def _fill_pages(store: Store) -> None:
    """From now on the file may not grow: the next write that needs a page gets SQLITE_FULL."""
    pages = store._conn.execute("PRAGMA page_count").fetchone()[0]
    store._conn.execute(f"PRAGMA max_page_count = {pages}")


def _lift(store: Store) -> None:
    store._conn.execute("PRAGMA max_page_count = 1073741823")


def test_a_write_on_a_full_store_is_store_full_error_and_nothing_is_lost(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.sqlite3")
    store.add_event("before", {"n": 1})
    _fill_pages(store)
    with pytest.raises(StoreFullError) as caught:
        for i in range(2000):  # each event a little larger than a page, until the file must grow
            store.add_event("filler", {"i": i, "pad": "x" * 5000})
    exc = caught.value
    assert exc.path == str(tmp_path / "s.sqlite3")
    assert str(tmp_path / "s.sqlite3") in str(exc) and "free" in str(exc)
    assert isinstance(exc.__cause__, sqlite3.OperationalError)  # the cause, not "no transaction is active"
    assert not store._conn.in_transaction
    kinds = [e.kind for e in store.list_events(limit=5000)]
    assert kinds[0] == "before" and kinds.count("filler") == i  # each committed write is whole
    _lift(store)
    store.add_event("after", {"n": 2})  # the same connection works once there is room
    assert store.list_events(limit=1, newest_first=True)[0].kind == "after"
    store.close()


async def test_a_write_on_a_full_disk_is_answered_507_naming_the_file(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    async with in_process_service(settings) as (client, store):

        async def upload(name: str, seed: int) -> httpx.Response:
            return await client.post(
                "/api/datasets",
                params={"name": name},
                content=campaign_csv(40, seed=seed),
                headers={**auth("engineer"), "Content-Type": "text/csv"},
            )

        assert (await upload("first", 0)).status_code == 201
        _fill_pages(store)
        r = await upload("second", 1)
        assert r.status_code == 507, r.text
        body = r.json()
        assert body["error"] == "insufficient_storage"
        (detail,) = body["details"]
        assert detail["path"] == str(settings.store.db_path) and isinstance(detail["free_bytes"], int)
        assert str(settings.store.db_path) in body["message"]
        listed = await client.get("/api/datasets", headers=auth("viewer"))
        assert [d["name"] for d in listed.json()] == ["first"]
        _lift(store)
        r = await upload("second", 1)
        assert r.status_code == 201, r.text


# ------------------------------------------------------------------------------ an emptied store


def test_a_new_store_gets_a_marker_and_an_emptied_one_is_refused(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, store={"data_dir": str(tmp_path / "data"), "backup_interval_h": 0})
    db = settings.store.db_path
    open_store(settings).close()  # a new store: created, with its marker
    assert store_files.marker_path(db).is_file()
    db.write_bytes(b"")
    with pytest.raises(StoreDamagedError) as caught:
        open_store(settings)
    words = str(caught.value)
    assert words.startswith(f"store {db} is empty (0 bytes) but a store existed there (marker ")
    assert "nothing was changed" in words and "move" in words  # no backup: how to start empty
    assert db.stat().st_size == 0
    db.unlink()
    with pytest.raises(StoreDamagedError, match="is missing but a store existed"):
        open_store(settings)
    assert not db.exists()


def test_backups_alone_show_that_a_store_existed(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    db, backups = settings.store.db_path, settings.store.backup_path
    store = open_store(settings)
    store.add_event("kept", {})
    store.close()
    store_files.make_backup(db, backups, keep=3)
    store_files.marker_path(db).unlink()
    db.write_bytes(b"")
    with pytest.raises(StoreDamagedError, match=r"1 backup\(s\) in .*store restore --config FILE"):
        open_store(settings)


def test_an_existing_store_without_marker_gets_one(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    Store(settings.store.db_path).close()  # a store of a version without markers
    open_store(settings).close()
    assert store_files.marker_path(settings.store.db_path).is_file()


def test_a_damaged_store_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    store = open_store(settings)
    for i in range(200):
        store.add_event("e", {"i": i, "pad": "y" * 200})
    store.close()
    db = settings.store.db_path
    conn = sqlite3.connect(db)
    root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'events'").fetchone()[0]
    page = conn.execute("PRAGMA page_size").fetchone()[0]
    conn.close()
    with db.open("r+b") as fh:
        fh.seek((root - 1) * page)
        fh.write(b"\x0d" + os.urandom(page - 1))
    before = db.read_bytes()
    words = f"store {db} is damaged: .*; nothing was changed; "
    with pytest.raises(StoreDamagedError, match=words) as caught:
        open_store(settings)
    assert "\n" not in str(caught.value)  # one line, however many problems the check found
    assert db.read_bytes() == before


# ------------------------------------------------------------------------------ backups and restore


def test_backups_are_rotated_and_checked(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    db, folder = settings.store.db_path, settings.store.backup_path
    store = open_store(settings)
    made = []
    for i in range(4):
        store.add_event("step", {"i": i})
        made.append(store_files.make_backup(db, folder, keep=2))
    kept = store_files.list_backups(folder, db)
    assert [b.path for b in kept] == [m.path for m in made[-2:]]
    assert not list(folder.glob("*.part"))
    assert store_files.check_file(kept[-1].path) == []
    conn = sqlite3.connect(kept[-1].path)
    assert conn.execute("SELECT COUNT(*) FROM events WHERE kind = 'step'").fetchone()[0] == 4
    conn.close()
    store.close()


def test_restore_refuses_while_the_store_is_in_use_and_keeps_the_replaced_files(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    db, folder = settings.store.db_path, settings.store.backup_path
    store = open_store(settings)
    store.add_event("in the backup", {})
    store_files.make_backup(db, folder, keep=3)
    store.add_event("after the backup", {})
    store.close()
    with store_files.StoreLock(db), pytest.raises(StoreError, match=f"in use by process {os.getpid()}"):
        store_files.restore(db, folder)
    db.write_bytes(b"")
    backup, aside = store_files.restore(db, folder)
    assert backup.path == store_files.list_backups(folder, db)[-1].path
    assert aside is not None and (aside / db.name).stat().st_size == 0
    store = open_store(settings)
    kinds = [e.kind for e in store.list_events(limit=100)]
    assert "in the backup" in kinds and "after the backup" not in kinds
    store.close()


def test_store_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    settings = make_settings(tmp_path)
    data_dir = str(settings.store.data_dir)
    store = open_store(settings)
    store.add_event("x", {})
    store.close()
    assert cli_main(["store", "backup", "--data-dir", data_dir]) == 0
    assert "backed up" in capsys.readouterr().out
    assert cli_main(["store", "check", "--data-dir", data_dir]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["rows"]["events"] >= 1 and len(doc["backups"]) == 1
    settings.store.db_path.write_bytes(b"not a database at all" * 300)
    assert cli_main(["store", "check", "--data-dir", data_dir]) == 3
    out = capsys.readouterr()
    assert "is damaged" in out.err and json.loads(out.out)["ok"] is False
    assert cli_main(["store", "restore", "--data-dir", data_dir]) == 0
    assert cli_main(["store", "check", "--data-dir", data_dir]) == 0
    assert cli_main(["store", "restore", "--data-dir", data_dir, "--backup", str(tmp_path / "nope")]) == 2
    assert "no backup file" in capsys.readouterr().err


# ------------------------------------------------------------------------------ a job on a full disk


async def _store_reasons(client: httpx.AsyncClient) -> list[str]:
    r = await client.get("/ready")
    return [s for s in r.json()["reasons"] if s.startswith("store not writable")]


async def _until(cond: Any, limit_s: float) -> Any:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        value = await cond()
        if value:
            return value
        await asyncio.sleep(0.1)
    raise AssertionError("condition not reached in time")


async def test_a_fit_finishing_on_a_full_disk_fails_naming_it_and_ready_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(jobs_module, "_FULL_RETRY_S", 0.2, raising=False)  # absent before the fix
    settings = make_settings(tmp_path, jobs={"workers": 1})
    db = str(settings.store.db_path)
    async with in_process_service(settings) as (client, store):
        up = await client.post(
            "/api/datasets",
            params={"name": "kept"},
            content=campaign_csv(60, seed=3),
            headers={**auth("engineer"), "Content-Type": "text/csv"},
        )
        assert up.status_code == 201, up.text
        assert await _store_reasons(client) == []
        finish = store.finish_job

        def finish_on_a_full_disk(*args: Any, **kwargs: Any) -> Any:
            _fill_pages(store)  # the disk fills up while the fit runs: its result needs room
            return finish(*args, **kwargs)

        monkeypatch.setattr(store, "finish_job", finish_on_a_full_disk)
        r = await client.post(
            "/api/fits", json={"dataset_id": up.json()["id"], "model": "kinematic"}, headers=auth("engineer")
        )
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        (reason,) = await _until(lambda: _store_reasons(client), 90.0)
        assert reason.startswith(f"store not writable: disk full: cannot write {db} (")
        assert (await client.get("/ready")).status_code == 503
        _lift(store)  # room again
        job = await job_done(client, job_id, limit_s=20.0)
        assert job["state"] == "failed", job
        assert job["error"].startswith(
            f"the job's result could not be stored: disk full: cannot write {db} ("
        )
        assert job["error"].endswith("run the job again once there is room")
        await _until(lambda: _not(_store_reasons(client)), 5.0)
        # nothing lost: the data set is there, no half-stored model, and the store takes writes
        listed = await client.get("/api/datasets", headers=auth("viewer"))
        assert [d["name"] for d in listed.json()] == ["kept"]
        assert (await client.get("/api/models", headers=auth("viewer"))).json() == []
        assert store.quick_check() == []


async def _not(awaitable: Any) -> bool:
    return not await awaitable


def test_write_problem_says_when_the_store_cannot_write_and_when_it_can_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = Store(tmp_path / "s.sqlite3")
    assert store.write_problem() is None
    _fill_pages(store)
    with pytest.raises(StoreFullError):
        for i in range(2000):
            store.add_event("filler", {"i": i, "pad": "x" * 5000})
    problem = store.write_problem()
    assert problem is not None and problem.startswith(
        f"store not writable: disk full: cannot write {store.path}"
    )
    count = len(store.list_events(limit=5000))
    monkeypatch.setattr(store_base, "PROBE_INTERVAL_S", 0.0)
    assert store.write_problem() == problem  # the trial write fails as well
    _lift(store)
    assert store.write_problem() is None  # the trial write works: writable again, before any real write
    assert len(store.list_events(limit=5000)) == count  # the trial left nothing behind
    # too little free space on the disk: not writable whatever the last write did
    monkeypatch.setattr(store_base, "free_bytes", lambda path: 4096)
    assert store.write_problem() == (
        f"store not writable: only 4096 bytes free on the disk of {store.path}; free space on that disk"
    )
    store.close()
