"""What the store's safety costs on a store of a plant's size: the ``PRAGMA quick_check`` at every
start, ``integrity_check`` (``comp-daemon store check --full``) and one online backup.

The store: 134 data sets of 11 000 CSV rows (0.7 MB each), 21 models and 248 finished targets, put
straight into the schema of :class:`comp_daemon.service.store.Store` (about 95 MB). Each figure is
the best and the worst of ``--repeats`` runs.

Run: ``python -m benchmarks.bench_store_checks [--repeats 3]``
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import tempfile
import time
from pathlib import Path

from benchmarks.machine import machine_line
from comp_daemon.service.store import Store
from comp_daemon.service.store import files as store_files

ROW = "12.5,-80.25,95.125,1.5,30.75,2.25,1500.123,200.456,1300.789,fit\n"


def build(db: Path, datasets: int = 134, models: int = 21, targets: int = 248, rows: int = 11_000) -> None:
    Store(db).close()
    content = "a1,a2,a3,a4,a5,a6,x,y,z,split\n" + ROW * rows
    now = time.time()
    conn = sqlite3.connect(db)
    with conn:
        for i in range(datasets):
            conn.execute(
                "INSERT INTO datasets (name, format, content, sha256, rows, summary, created_at)"
                " VALUES (?, 'csv', ?, ?, ?, '{}', ?)",
                (f"campaign-{i}", content, "0" * 64, rows, now),
            )
        artifact = json.dumps({"params": list(range(2000))})
        for _ in range(models):
            conn.execute(
                "INSERT INTO models (kind, artifact, stats, created_at) VALUES ('kinematic', ?, '{}', ?)",
                (artifact, now),
            )
        conn.execute(
            "INSERT INTO batches (idempotency_key, request_sha256, size, created_at) VALUES ('b', 'x', ?, ?)",
            (targets, now),
        )
        for i in range(targets):
            conn.execute(
                "INSERT INTO targets (batch_id, idempotency_key, seq, queue_pos, request, state, created_at,"
                " updated_at) VALUES (1, ?, ?, ?, '{}', 'done', ?, ?)",
                (f"t{i}", i, i, now, now),
            )
    conn.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(machine_line())
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "comp-daemon.sqlite3"
        build(db)
        print(f"store: {db.stat().st_size / 1e6:.1f} MB")
        times: dict[str, list[float]] = {"open with quick_check": [], "integrity_check": [], "backup": []}
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            Store(db, check=True).close()
            times["open with quick_check"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            assert store_files.check_file(db, full=True) == []
            times["integrity_check"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            store_files.make_backup(db, Path(tmp) / "backups", keep=1)
            times["backup"].append(time.perf_counter() - t0)
        for what, values in times.items():
            print(f"{what}: {min(values):.2f} to {max(values):.2f} s")


if __name__ == "__main__":
    main()
