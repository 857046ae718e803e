"""The job table in SQLite (WAL), the truth every process shares: API workers store and read
jobs, the scheduler moves them through their states. Every state change is a
compare-and-set, so terminal states are final whatever races them. The events table is the
notification channel: state snapshots and tiles appended by whoever changed the job, read
in order by every API worker (nprt.service.feed)."""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from pydantic_core import from_json

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
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id TEXT NOT NULL,
    at REAL NOT NULL,
    kind TEXT NOT NULL,
    body TEXT NOT NULL,
    rgb BLOB
);
"""
BUSY_TIMEOUT_S = 10.0  # a writer waits this long for another process's write, then errors
# Columns added after the first release: a database written by an older service gains them.
_ADDED_COLUMNS = {
    "cancel_requested": "INTEGER NOT NULL DEFAULT 0",
    "retries": "INTEGER NOT NULL DEFAULT 0",
    "idempotency_key": "TEXT",
    "frames": "TEXT",  # JSON [first, last] of an animated scene's frame range, or NULL
}
_INDEXES = "CREATE UNIQUE INDEX IF NOT EXISTS jobs_idempotency_key ON jobs(idempotency_key);"
# The queue depth as a counter kept by triggers: admission reads one row, not a count over
# every queued job. Recounted once per open, in the transaction that makes the triggers.
_QUEUE_COUNTER = """
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, n INTEGER NOT NULL);
INSERT OR IGNORE INTO counters VALUES ('queued', 0);
CREATE TRIGGER IF NOT EXISTS jobs_queued_insert AFTER INSERT ON jobs WHEN NEW.state = 'queued'
BEGIN UPDATE counters SET n = n + 1 WHERE name = 'queued'; END;
CREATE TRIGGER IF NOT EXISTS jobs_queued_update AFTER UPDATE OF state ON jobs
WHEN (OLD.state = 'queued') != (NEW.state = 'queued')
BEGIN UPDATE counters SET n = n + (CASE WHEN NEW.state = 'queued' THEN 1 ELSE -1 END)
WHERE name = 'queued'; END;
CREATE TRIGGER IF NOT EXISTS jobs_queued_delete AFTER DELETE ON jobs WHEN OLD.state = 'queued'
BEGIN UPDATE counters SET n = n - 1 WHERE name = 'queued'; END;
UPDATE counters SET n = (SELECT COUNT(*) FROM jobs WHERE state = 'queued')
WHERE name = 'queued';
"""
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
    # The settings as stored (JSON text): a key for reusing their validated model.
    settings_json: str | None = field(default=None, compare=False, repr=False)

    @property
    def progress(self) -> float:
        return min(1.0, self.passes_done / self.passes_total) if self.passes_total else 0.0


class QueueFull(RuntimeError):
    """insert() found max_queued jobs queued already; the message says how many."""


def add_columns(db: sqlite3.Connection, have: set[str]) -> None:
    """Add the columns of _ADDED_COLUMNS missing from `have` (the jobs table's columns as
    read). Processes open the store at once (API workers, the gRPC child, the scheduler):
    one that read the columns before another added one finds it there, which is fine."""
    for name, decl in _ADDED_COLUMNS.items():
        if name in have:
            continue
        try:
            db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {decl}")
        except sqlite3.OperationalError as e:
            if "duplicate column name" not in str(e):
                raise


class JobStore:
    """A writing and a reading connection, each behind its own lock: writes are tiny (one
    row per pass) and SQLite serialises writers anyway; in WAL mode a read never waits for
    a write, so a reader here never queues behind a writer waiting for another process."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None,
                                   timeout=BUSY_TIMEOUT_S)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            # NORMAL is durable across process crashes in WAL mode; only power loss can drop
            # the last commits, and checkpoints on disk are re-read on restart anyway.
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
            add_columns(self._db, {r["name"] for r in self._db.execute(
                "PRAGMA table_info(jobs)")})
            self._db.executescript(_INDEXES)
            self._db.executescript(f"BEGIN IMMEDIATE;{_QUEUE_COUNTER}COMMIT;")
        self._rdb = sqlite3.connect(path, check_same_thread=False, isolation_level=None,
                                    timeout=BUSY_TIMEOUT_S)
        self._rdb.row_factory = sqlite3.Row
        self._rlock = threading.Lock()

    def close(self) -> None:
        with self._lock, self._rlock:
            self._db.close()
            self._rdb.close()

    def _read(self, sql: str, args: tuple = ()) -> list[sqlite3.Row]:
        with self._rlock:
            return self._rdb.execute(sql, args).fetchall()

    def insert(self, job_id: str, scene: str, settings: dict | str, passes_total: int,
               idempotency_key: str | None = None,
               frames: list[int] | None = None, max_queued: int | None = None) -> JobRecord:
        """Store a queued job; settings as a dict or as its JSON text (stored as given; the
        record has it parsed). With an idempotency key that is already stored, nothing is
        inserted and the stored job is returned (compare its id to tell). With max_queued,
        QueueFull when that many jobs are queued (checked in the same statement, so
        concurrent inserts from any process never overshoot it; O(1), a counter)."""
        out = self.insert_many([(job_id, scene, settings, passes_total, idempotency_key,
                                 frames, max_queued)])[0]
        if isinstance(out, QueueFull):
            raise out
        return out

    def insert_many(self, rows: list[tuple]) -> list[JobRecord | QueueFull]:
        """insert(*row) for every row, in one write transaction (one commit for a burst of
        admissions); a row refused for the queue depth gets its QueueFull in the list, the
        others are stored."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                out = [self._insert(*row) for row in rows]
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return out

    def _insert(self, job_id: str, scene: str, settings: dict | str, passes_total: int,
                idempotency_key: str | None, frames: list[int] | None,
                max_queued: int | None) -> JobRecord | QueueFull:
        now = time.time()
        depth = -1 if max_queued is None else max_queued
        if isinstance(settings, str):  # JSON text already (an admission's, from pydantic)
            settings_json, settings = settings, from_json(settings)
        else:
            settings_json = json.dumps(settings)
        cur = self._db.execute(
            "INSERT INTO jobs (id, scene, settings, state, created_at, passes_total, "
            "idempotency_key, frames) SELECT ?, ?, ?, 'queued', ?, ?, ?, ? WHERE ? < 0 OR "
            "(SELECT n FROM counters WHERE name = 'queued') < ? "
            "ON CONFLICT (idempotency_key) DO NOTHING",
            (job_id, scene, settings_json, now, passes_total, idempotency_key,
             None if frames is None else json.dumps(list(frames)), depth, depth))
        if cur.rowcount == 0:
            row = None if idempotency_key is None else self._db.execute(
                "SELECT * FROM jobs WHERE idempotency_key = ?", (idempotency_key,)).fetchone()
            if row is None:
                return QueueFull(f"{max_queued} jobs are queued, the limit "
                                 "(NPRT_MAX_QUEUED_JOBS)")
            return _record(row)  # the key was stored already
        return JobRecord(seq=cur.lastrowid, id=job_id, scene=scene, settings=settings,
                         state="queued", created_at=now, started_at=None, finished_at=None,
                         passes_done=0, passes_total=passes_total, error=None, stats=None,
                         pixel_samples=None, idempotency_key=idempotency_key,
                         frames=None if frames is None else list(frames),
                         settings_json=settings_json)

    def get(self, job_id: str) -> JobRecord | None:
        rows = self._read("SELECT * FROM jobs WHERE id = ?", (job_id,))
        return _record(rows[0]) if rows else None

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
        with self._rlock:
            rows = self._rdb.execute(f"SELECT * FROM jobs {where} ORDER BY seq DESC "
                                     "LIMIT ? OFFSET ?", (*args, limit, offset)).fetchall()
            total = self._rdb.execute(f"SELECT COUNT(*) FROM jobs {where}", args).fetchone()[0]
        return [_record(r) for r in rows], int(total)

    def counts_by_state(self) -> dict[str, int]:
        """Jobs per state; every state is a key."""
        rows = self._read("SELECT state, COUNT(*) FROM jobs GROUP BY state")
        return {s: 0 for s in STATES} | {r[0]: int(r[1]) for r in rows}

    def active_or_finished_since(self, t: float) -> list[JobRecord]:
        """Jobs preparing or running now, and jobs that finished at or after t (unix s)."""
        rows = self._read("SELECT * FROM jobs WHERE state IN ('preparing', 'running') "
                          "OR finished_at >= ?", (t,))
        return [_record(r) for r in rows]

    def unfinished(self) -> list[JobRecord]:
        """Jobs a previous process left behind, oldest first (FIFO on restart)."""
        rows = self._read(f"SELECT * FROM jobs WHERE {_UNFINISHED_SQL} ORDER BY seq")
        return [_record(r) for r in rows]

    # ------------------------------------------------------------ scheduler's queue

    def queued_after(self, seq: int) -> list[tuple[int, str]]:
        """(seq, id) of queued jobs stored after `seq`, oldest first. Writers commit one at
        a time in seq order, so a reader that moves past a seq never misses a lower one."""
        rows = self._read("SELECT seq, id FROM jobs WHERE state = 'queued' AND seq > ? "
                          "ORDER BY seq", (seq,))
        return [(int(r[0]), r[1]) for r in rows]

    def max_seq(self) -> int:
        return int(self._read("SELECT COALESCE(MAX(seq), 0) FROM jobs")[0][0])

    def cancels_among(self, job_ids: list[str]) -> set[str]:
        """The ids among job_ids whose cancel is stored."""
        if not job_ids:
            return set()
        marks = ",".join("?" * len(job_ids))
        return {r[0] for r in self._read(
            f"SELECT id FROM jobs WHERE cancel_requested AND id IN ({marks})", tuple(job_ids))}

    # ------------------------------------------------------------ events

    def state_event(self, job_id: str) -> None:
        """Append the job's record as it is now; read and appended in one write
        transaction, so the events of a job are in the order its states changed."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                row = self._db.execute("SELECT * FROM jobs WHERE id = ?",
                                       (job_id,)).fetchone()
                if row is not None:
                    self._db.execute("INSERT INTO events (job_id, at, kind, body) "
                                     "VALUES (?, ?, 'state', ?)",
                                     (job_id, time.time(), json.dumps(dict(row))))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def tile_event(self, job_id: str, tile: dict, rgb: bytes) -> None:
        """Append one finished pass: tile is the TileEvent fields, rgb the tile's pixels
        as float32 bytes."""
        self._execute("INSERT INTO events (job_id, at, kind, body, rgb) "
                      "VALUES (?, ?, 'tile', ?, ?)", (job_id, time.time(), json.dumps(tile), rgb))

    def events_after(self, seq: int, limit: int = 1000) -> list[tuple]:
        """(seq, job_id, kind, body, rgb) of events after `seq`, oldest first."""
        return [tuple(r) for r in self._read(
            "SELECT seq, job_id, kind, body, rgb FROM events WHERE seq > ? ORDER BY seq "
            "LIMIT ?", (seq, limit))]

    def max_event_seq(self) -> int:
        return int(self._read("SELECT COALESCE(MAX(seq), 0) FROM events")[0][0])

    def prune_events(self, tiles_before: float, states_before: float) -> None:
        """Forget tile events appended before tiles_before and state events before
        states_before (unix s): watchers read within a poll, and tiles are the bulk."""
        self._execute("DELETE FROM events WHERE at < ? AND (kind = 'tile' OR at < ?)",
                      (tiles_before, states_before))

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
    d["settings_json"] = d["settings"]
    for k in _JSON_COLUMNS:
        d[k] = json.loads(d[k]) if d[k] is not None else None
    d["cancel_requested"] = bool(d["cancel_requested"])
    return JobRecord(**d)


def record_from_json(text: str) -> JobRecord:
    """The JobRecord of a state event's body (a jobs row as JSON)."""
    return _record(json.loads(text))
