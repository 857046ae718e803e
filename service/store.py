"""The job table in SQLite (WAL): every job is stored here before it runs, and every state
change is a compare-and-set, so terminal states are final whatever races them."""

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
# Columns added after the first release: a database written by an older service gains them.
_ADDED_COLUMNS = {
    "cancel_requested": "INTEGER NOT NULL DEFAULT 0",
    "retries": "INTEGER NOT NULL DEFAULT 0",
    "idempotency_key": "TEXT",
    "frames": "TEXT",  # JSON [first, last] of an animated scene's frame range, or NULL
}
_INDEXES = "CREATE UNIQUE INDEX IF NOT EXISTS jobs_idempotency_key ON jobs(idempotency_key);"
_JSON_COLUMNS = ("settings", "stats", "pixel_samples", "frames")
_UPDATABLE = frozenset({"started_at", "finished_at", "passes_done", "passes_total", "error",
                        "stats", "pixel_samples"})
_UNFINISHED_SQL = "state IN ('queued', 'preparing', 'running')"


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
    cancel_requested: bool = False
    retries: int = 0  # times the job went back to the queue after losing its Ray shards
    idempotency_key: str | None = None
    frames: list[int] | None = None  # [first, last] frame rendered, inclusive; None: one image

    @property
    def progress(self) -> float:
        return min(1.0, self.passes_done / self.passes_total) if self.passes_total else 0.0


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
            have = {r["name"] for r in self._db.execute("PRAGMA table_info(jobs)")}
            for name, decl in _ADDED_COLUMNS.items():
                if name not in have:
                    self._db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {decl}")
            self._db.executescript(_INDEXES)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def insert(self, job_id: str, scene: str, settings: dict, passes_total: int,
               idempotency_key: str | None = None,
               frames: list[int] | None = None) -> JobRecord:
        """Store a queued job. With an idempotency key that is already stored, nothing is
        inserted and the stored job is returned (compare its id to tell)."""
        now = time.time()
        with self._lock:
            cur = self._db.execute(
                "INSERT INTO jobs (id, scene, settings, state, created_at, passes_total, "
                "idempotency_key, frames) VALUES (?, ?, ?, 'queued', ?, ?, ?, ?) "
                "ON CONFLICT (idempotency_key) DO NOTHING",
                (job_id, scene, json.dumps(settings), now, passes_total, idempotency_key,
                 None if frames is None else json.dumps(list(frames))))
            if cur.rowcount == 0:  # the key was stored already
                row = self._db.execute("SELECT * FROM jobs WHERE idempotency_key = ?",
                                       (idempotency_key,)).fetchone()
                return _record(row)
        return JobRecord(seq=cur.lastrowid, id=job_id, scene=scene, settings=settings,
                         state="queued", created_at=now, started_at=None, finished_at=None,
                         passes_done=0, passes_total=passes_total, error=None, stats=None,
                         pixel_samples=None, idempotency_key=idempotency_key,
                         frames=None if frames is None else list(frames))

    def get(self, job_id: str) -> JobRecord | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _record(row) if row else None

    def update(self, job_id: str, **fields) -> bool:
        """Set non-state fields of an unfinished job (progress, stats); a finished job's
        record is final. Returns whether a row changed."""
        bad = set(fields) - _UPDATABLE
        if bad:
            raise ValueError(f"not updatable job fields: {sorted(bad)}; states change through "
                             "transition() and finish()")
        cols, values = _assignments(fields)
        return self._execute(f"UPDATE jobs SET {cols} WHERE id = ? AND {_UNFINISHED_SQL}",
                             (*values, job_id))

    def transition(self, job_id: str, state: str, from_states: tuple[str, ...],
                   **fields) -> bool:
        """Compare-and-set: move to `state` only from one of `from_states`; returns whether
        it happened. Terminal states go through finish(), which honours a stored cancel."""
        _check_state(state)
        if state in TERMINAL or TERMINAL & set(from_states):
            raise ValueError(f"transition {from_states} -> {state!r}: terminal states are "
                             "entered through finish() and never left")
        cols, values = _assignments({"state": state, **fields})
        marks = ",".join("?" * len(from_states))
        return self._execute(f"UPDATE jobs SET {cols} WHERE id = ? AND state IN ({marks})",
                             (*values, job_id, *from_states))

    def finish(self, job_id: str, state: str, **fields) -> str | None:
        """Move an unfinished job to the terminal `state` and return the state it got: a job
        whose cancel was stored ends canceled rather than succeeded. None if it had
        already finished (nothing changes then)."""
        _check_state(state)
        if state not in TERMINAL:
            raise ValueError(f"finish() takes a terminal state {sorted(TERMINAL)}, "
                             f"got {state!r}")
        cols, values = _assignments(fields)
        sets = (f"{cols}, " if cols else "") + (
            "state = CASE WHEN cancel_requested AND ? = 'succeeded' THEN 'canceled' ELSE ? END")
        with self._lock:
            changed = self._db.execute(
                f"UPDATE jobs SET {sets} WHERE id = ? AND {_UNFINISHED_SQL}",
                (*values, state, state, job_id)).rowcount
            if not changed:
                return None
            return self._db.execute("SELECT state FROM jobs WHERE id = ?",
                                    (job_id,)).fetchone()[0]

    def request_cancel(self, job_id: str) -> bool:
        """Store a cancel before anyone acts on it: a queued job is canceled at once, a
        preparing or running one keeps its state until its renderer stops (or, after a
        restart, is canceled on start). False if the job is unknown or already finished."""
        return self._execute(
            "UPDATE jobs SET cancel_requested = 1, "
            "finished_at = CASE WHEN state = 'queued' THEN ? ELSE finished_at END, "
            "state = CASE WHEN state = 'queued' THEN 'canceled' ELSE state END "
            f"WHERE id = ? AND {_UNFINISHED_SQL}", (time.time(), job_id))

    def requeue(self, job_id: str, max_retries: int, **fields) -> bool:
        """Put a preparing or running job back in the queue, counting one more retry; False
        once it has had max_retries, or if a cancel was stored meanwhile."""
        cols, values = _assignments({"state": "queued", **fields})
        return self._execute(
            f"UPDATE jobs SET {cols}, retries = retries + 1 WHERE id = ? AND "
            "state IN ('preparing', 'running') AND NOT cancel_requested AND retries < ?",
            (*values, job_id, max_retries))

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
        with self._lock:
            rows = self._db.execute(f"SELECT * FROM jobs WHERE {_UNFINISHED_SQL} "
                                    "ORDER BY seq").fetchall()
        return [_record(r) for r in rows]

    def _execute(self, sql: str, args: tuple) -> bool:
        with self._lock:
            return self._db.execute(sql, args).rowcount > 0


def _check_state(state: str) -> None:
    if state not in STATES:
        raise ValueError(f"unknown job state {state!r}; expected one of {STATES}")


def _assignments(fields: dict) -> tuple[str, list]:
    """('a = ?, b = ?', values), JSON-encoding the JSON columns."""
    values = [json.dumps(v) if k in _JSON_COLUMNS and v is not None else v
              for k, v in fields.items()]
    return ", ".join(f"{k} = ?" for k in fields), values


def _record(row: sqlite3.Row) -> JobRecord:
    d = dict(row)
    for k in _JSON_COLUMNS:
        d[k] = json.loads(d[k]) if d[k] is not None else None
    d["cancel_requested"] = bool(d["cancel_requested"])
    return JobRecord(**d)
