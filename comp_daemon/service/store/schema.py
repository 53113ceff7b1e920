"""The schema of the store's SQLite file: ordered migrations, each applied once in its own transaction."""

from __future__ import annotations

__all__ = ["MIGRATIONS", "SCHEMA_VERSION"]

MIGRATIONS: tuple[tuple[int, tuple[str, ...]], ...] = (
    (
        1,
        (
            """CREATE TABLE datasets (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                name TEXT NOT NULL,
                format TEXT NOT NULL CHECK (format IN ('csv', 'json')),
                content TEXT NOT NULL,
                sha256 TEXT NOT NULL,
                rows INTEGER NOT NULL CHECK (rows >= 0),
                summary TEXT NOT NULL,
                created_at REAL NOT NULL)""",
            """CREATE TABLE jobs (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                kind TEXT NOT NULL,
                params TEXT NOT NULL,
                dataset_id INTEGER REFERENCES datasets(id) ON DELETE SET NULL,
                state TEXT NOT NULL
                    CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
                progress REAL NOT NULL DEFAULT 0,
                message TEXT,
                result TEXT,
                error TEXT,
                created_at REAL NOT NULL,
                started_at REAL,
                finished_at REAL)""",
            "CREATE INDEX jobs_state ON jobs(state)",
            """CREATE TABLE models (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                kind TEXT NOT NULL,
                "order" INTEGER,
                artifact TEXT NOT NULL,
                stats TEXT NOT NULL,
                dataset_id INTEGER REFERENCES datasets(id) ON DELETE SET NULL,
                job_id INTEGER REFERENCES jobs(id) ON DELETE SET NULL,
                active INTEGER NOT NULL DEFAULT 0 CHECK (active IN (0, 1)),
                created_at REAL NOT NULL)""",
            "CREATE UNIQUE INDEX models_one_active ON models(active) WHERE active = 1",
            """CREATE TABLE batches (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                idempotency_key TEXT NOT NULL UNIQUE,
                request_sha256 TEXT NOT NULL,
                source TEXT,
                size INTEGER NOT NULL CHECK (size >= 1),
                created_at REAL NOT NULL)""",
            """CREATE TABLE targets (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                batch_id INTEGER NOT NULL REFERENCES batches(id),
                idempotency_key TEXT NOT NULL UNIQUE,
                seq INTEGER NOT NULL,
                queue_pos INTEGER NOT NULL,
                request TEXT NOT NULL,
                state TEXT NOT NULL CHECK (state IN ('queued', 'compensating', 'moving', 'settling',
                    'done', 'failed', 'cancelled', 'interrupted')),
                reason TEXT,
                commanded_axes TEXT,
                final_joint_errors TEXT,
                created_at REAL NOT NULL,
                updated_at REAL NOT NULL,
                started_at REAL,
                finished_at REAL,
                UNIQUE (batch_id, seq))""",
            "CREATE INDEX targets_state_pos ON targets(state, queue_pos)",
            "CREATE INDEX targets_batch ON targets(batch_id, seq)",
            """CREATE TABLE events (
                id INTEGER PRIMARY KEY AUTOINCREMENT,
                time REAL NOT NULL,
                kind TEXT NOT NULL,
                target_id INTEGER REFERENCES targets(id),
                job_id INTEGER REFERENCES jobs(id),
                message TEXT NOT NULL)""",
            "CREATE INDEX events_time ON events(time)",
            "CREATE INDEX events_target ON events(target_id)",
            "CREATE INDEX events_job ON events(job_id)",
        ),
    ),
)
SCHEMA_VERSION = MIGRATIONS[-1][0]
