"""The job table in SQLite (WAL): every job is stored here before it runs."""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path

STATES = ("queued", "preparing", "running", "succeeded", "failed", "canceled")
TERMINAL = frozenset({"succeeded", "failed", "canceled"})
UNFINISHED = ("queued", "preparing", "running")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    scene TEXT NOT NULL,
    settings TEXT NOT NULL,
    state TEXT NOT NULL,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    passes_done INTEGER NOT NULL DEFAULT 0,
    passes_total INTEGER NOT NULL DEFAULT 0,
    error TEXT,
    stats TEXT,
    pixel_samples TEXT
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
"""
_JSON_COLUMNS = ("settings", "stats", "pixel_samples")
_UPDATABLE = frozenset({"state", "started_at", "finished_at", "passes_done", "passes_total",
                        "error", "stats", "pixel_samples"})


@dataclass
class JobRecord:
    seq: int
    id: str
    scene: str
    settings: dict
    state: str
    created_at: float
    started_at: float | None
    finished_at: float | None
    passes_done: int
    passes_total: int
    error: str | None
    stats: dict | None
    pixel_samples: dict | None

    @property
    def progress(self) -> float:
        return self.passes_done / self.passes_total if self.passes_total else 0.0


class JobStore:
    """One connection behind a lock: writes are tiny (one row per pass) and SQLite
    serialises writers anyway."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            # NORMAL is durable across process crashes in WAL mode; only power loss can drop
            # the last commits, and checkpoints on disk are re-read on restart anyway.
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def insert(self, job_id: str, scene: str, settings: dict, passes_total: int) -> JobRecord:
        with self._lock:
            self._db.execute(
                "INSERT INTO jobs (id, scene, settings, state, created_at, passes_total) "
                "VALUES (?, ?, ?, 'queued', ?, ?)",
                (job_id, scene, json.dumps(settings), time.time(), passes_total))
        return self.get(job_id)

    def get(self, job_id: str) -> JobRecord | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _record(row) if row else None

    def update(self, job_id: str, **fields) -> None:
        bad = set(fields) - _UPDATABLE
        if bad:
            raise ValueError(f"not updatable job fields: {sorted(bad)}")
        if "state" in fields and fields["state"] not in STATES:
            raise ValueError(f"unknown job state {fields['state']!r}; expected one of {STATES}")
        values = [json.dumps(v) if k in _JSON_COLUMNS and v is not None else v
                  for k, v in fields.items()]
        cols = ", ".join(f"{k} = ?" for k in fields)
        with self._lock:
            self._db.execute(f"UPDATE jobs SET {cols} WHERE id = ?", (*values, job_id))

    def delete(self, job_id: str) -> bool:
        """Remove the job's row; False if there was none."""
        with self._lock:
            return self._db.execute("DELETE FROM jobs WHERE id = ?", (job_id,)).rowcount > 0

    def list(self, offset: int = 0, limit: int = 50, state: str | None = None
             ) -> tuple[list[JobRecord], int]:
        """A page of jobs, newest first, and the count of all matching jobs."""
        where, args = ("WHERE state = ?", (state,)) if state else ("", ())
        with self._lock:
            rows = self._db.execute(f"SELECT * FROM jobs {where} ORDER BY seq DESC "
                                    "LIMIT ? OFFSET ?", (*args, limit, offset)).fetchall()
            total = self._db.execute(f"SELECT COUNT(*) FROM jobs {where}", args).fetchone()[0]
        return [_record(r) for r in rows], int(total)

    def counts_by_state(self) -> dict[str, int]:
        """Jobs per state; every state is a key."""
        with self._lock:
            rows = self._db.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state").fetchall()
        return {s: 0 for s in STATES} | {r[0]: int(r[1]) for r in rows}

    def active_or_finished_since(self, t: float) -> list[JobRecord]:
        """Jobs preparing or running now, and jobs that finished at or after t (unix s)."""
        with self._lock:
            rows = self._db.execute("SELECT * FROM jobs WHERE state IN ('preparing', 'running') "
                                    "OR finished_at >= ?", (t,)).fetchall()
        return [_record(r) for r in rows]

    def unfinished(self) -> list[JobRecord]:
        """Jobs a previous process left behind, oldest first (FIFO on restart)."""
        marks = ",".join("?" * len(UNFINISHED))
        with self._lock:
            rows = self._db.execute(f"SELECT * FROM jobs WHERE state IN ({marks}) "
                                    "ORDER BY seq", UNFINISHED).fetchall()
        return [_record(r) for r in rows]


def _record(row: sqlite3.Row) -> JobRecord:
    d = dict(row)
    for k in _JSON_COLUMNS:
        d[k] = json.loads(d[k]) if d[k] is not None else None
    return JobRecord(**d)
