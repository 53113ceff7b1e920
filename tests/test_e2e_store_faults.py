"""The store's faults with the real daemon process: a zero-length, truncated or damaged database at
start, and a full disk (a small tmpfs) while it runs and at start.

What must hold (docs/reliability.md, "A full disk" and "A damaged or emptied store"): a store that
existed and is now empty or damaged is refused with one line (what, where, how to recover), exit 3,
the file untouched, no traceback; ``comp-daemon store restore`` brings the last backup back. On a
full disk writes are answered 507 naming the file and the free space while the daemon keeps
serving; nothing stored is lost; a start on the full disk is one line and exit 3.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from e2e_daemon import DaemonProcess, sample_campaign, upload_campaign

EXIT_STORE = 3


def _store_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "comp_daemon", "store", *args], capture_output=True, text=True, timeout=120
    )


def _refused(daemon: DaemonProcess, timeout_s: float = 120.0) -> tuple[int, str]:
    """Start ``daemon``, wait for it to exit; its exit code and the last line of its output."""
    daemon.start()
    assert daemon.proc is not None
    try:
        code = daemon.proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"the daemon did not refuse to start:\n{daemon.tail()}") from None
    text = daemon.log_text()
    assert "Traceback" not in text, text
    return code, text.strip().splitlines()[-1]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return sample_campaign(tmp_path_factory.mktemp("campaign") / "campaign.csv", n=40)


@pytest.fixture(scope="module")
def populated(tmp_path_factory: pytest.TempPathFactory, campaign: Path) -> Iterator[Path]:
    """A data folder written by a real daemon: two data sets, an online backup taken while it ran."""
    daemon = DaemonProcess(tmp_path_factory.mktemp("populated"), sim=False)
    try:
        daemon.start()
        daemon.wait_http()
        with daemon.client("engineer") as c:
            upload_campaign(c, campaign, name="first")
            upload_campaign(c, campaign, name="second")
        backup = _store_cli("backup", "--config", str(daemon.config_path))
        assert backup.returncode == 0, backup.stderr
        assert daemon.sigterm() == 0, daemon.tail()
    finally:
        daemon.cleanup()
    yield daemon.data_dir


def _daemon_on_copy(root: Path, populated: Path) -> DaemonProcess:
    daemon = DaemonProcess(root, sim=False)
    shutil.copytree(populated, daemon.data_dir)
    return daemon


def _rows(config: Path) -> dict[str, Any]:
    check = _store_cli("check", "--config", str(config))
    assert check.returncode == 0, check.stdout + check.stderr
    doc: dict[str, Any] = json.loads(check.stdout)
    return doc


def test_a_zero_length_store_that_existed_is_refused_and_restored(tmp_path: Path, populated: Path) -> None:
    daemon = _daemon_on_copy(tmp_path, populated)
    db = daemon.data_dir / "comp-daemon.sqlite3"
    for side in ("-wal", "-shm"):
        Path(f"{db}{side}").unlink(missing_ok=True)
    db.write_bytes(b"")
    try:
        started = time.monotonic()
        code, line = _refused(daemon)
        refused_s = time.monotonic() - started
    finally:
        daemon.cleanup()
    assert code == EXIT_STORE, daemon.tail()
    words = f"comp-daemon run: cannot start: store {db} is empty (0 bytes) but a store existed"
    assert line.startswith(words), line
    assert "store restore --config" in line and "backup" in line, line
    assert db.stat().st_size == 0, "the refused start changed the file"
    print(f"refused in {refused_s:.1f} s: {line}")

    restore = _store_cli("restore", "--config", str(daemon.config_path))
    assert restore.returncode == 0, restore.stderr
    doc = _rows(daemon.config_path)
    assert doc["rows"]["datasets"] == 2, doc  # both data sets of the online backup are back


def _truncate(db: Path) -> None:
    data = db.read_bytes()
    db.write_bytes(data[: len(data) // 2])


def _damage(db: Path) -> None:
    """Overwrite the first page of the data sets' table with garbage (a disk or a copy gone wrong)."""
    conn = sqlite3.connect(db)
    try:
        page_size = conn.execute("PRAGMA page_size").fetchone()[0]
        root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'datasets'").fetchone()[0]
    finally:
        conn.close()
    with db.open("r+b") as fh:
        fh.seek((root - 1) * page_size)
        fh.write(bytes(range(256)) * (page_size // 256))


@pytest.mark.parametrize("spoil", [_truncate, _damage], ids=["truncated", "damaged"])
def test_a_truncated_or_damaged_store_is_refused_with_one_line(
    tmp_path: Path, populated: Path, spoil: Any
) -> None:
    daemon = _daemon_on_copy(tmp_path, populated)
    db = daemon.data_dir / "comp-daemon.sqlite3"
    spoil(db)
    before = _sha256(db)
    try:
        code, line = _refused(daemon)
    finally:
        daemon.cleanup()
    assert code == EXIT_STORE, daemon.tail()
    assert line.startswith(f"comp-daemon run: cannot start: store {db} is damaged: "), line
    assert "store restore --config" in line, line
    assert _sha256(db) == before, "the refused start changed the file"
    check = _store_cli("check", "--config", str(daemon.config_path))
    assert check.returncode == EXIT_STORE, check.stdout


# ------------------------------------------------------------------------------------ a full disk


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 24 MB tmpfs at ``tmp_path/data`` (the daemon's data folder); skipped where mounts are refused."""
    mount = tmp_path / "data"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=24m,mode=0700", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        why = done.stderr.strip()
        pytest.skip(f"cannot mount a tmpfs here ({why}); the injected SQLITE_FULL tests stand in")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def _fill(folder: Path) -> Path:
    """Fill the disk of ``folder`` to the last byte; returns the filler file."""
    filler = folder / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        for size in (1 << 20, 1 << 16, 1 << 12, 1 << 9, 1):
            block = b"\0" * size
            with contextlib.suppress(OSError):
                while True:
                    os.write(fd, block)
    finally:
        os.close(fd)
    return filler


def test_a_full_disk_answers_507_keeps_serving_loses_nothing_and_refuses_to_start(
    tmp_path: Path, small_disk: Path, campaign: Path
) -> None:
    daemon = DaemonProcess(tmp_path, sim=False)
    assert daemon.data_dir == small_disk
    db = daemon.data_dir / "comp-daemon.sqlite3"
    try:
        daemon.start()
        daemon.wait_http()
        with daemon.client("engineer") as c:
            first = upload_campaign(c, campaign, name="before the disk filled")
            filler = _fill(small_disk)
            answers = []
            for _ in range(3):  # the first failed commit, and the ones after it
                r = c.post(
                    "/api/datasets",
                    params={"name": "on a full disk"},
                    content=campaign.read_bytes(),
                    headers={"Content-Type": "text/csv"},
                )
                answers.append(r)
            for r in answers:
                assert r.status_code == 507, r.text
                body = r.json()
                assert body["error"] == "insufficient_storage", body
                assert body["details"][0]["path"] == str(db), body
                assert body["details"][0]["free_bytes"] is not None, body
                assert str(db) in body["message"] and "free" in body["message"], body
            r = c.post(
                "/api/batches",
                json={"targets": [{"a1": 0, "a2": -90, "a3": 90, "a4": 0, "a5": 45, "a6": 0}]},
                headers={"Idempotency-Key": "on-a-full-disk"},
            )
            assert r.status_code == 507, r.text
            # the daemon keeps serving, and everything stored before is there
            assert c.get("/health").status_code == 200
            names = [d["name"] for d in c.get("/api/datasets").json()]
            assert names == ["before the disk filled"], names
            assert daemon.proc is not None and daemon.proc.poll() is None, daemon.tail()
            # space again: writes work without a restart
            filler.unlink()
            second = upload_campaign(c, campaign, name="after space was freed")
            assert second["id"] > first["id"]
        filler = _fill(small_disk)
        assert daemon.sigterm() == 0, daemon.tail()
        # a start on the full disk: one line, exit 3, no traceback
        code, line = _refused(daemon)
        assert code == EXIT_STORE, daemon.tail()
        assert line.startswith(f"comp-daemon run: cannot start: disk full: cannot write {db}"), line
        assert "free space" in line, line
        filler.unlink()
    finally:
        daemon.cleanup()
    doc = _rows(daemon.config_path)
    assert doc["rows"]["datasets"] == 2, doc  # data lost: none
