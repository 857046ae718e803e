"""The SQLite job store and the per-pass checkpoint files."""

from __future__ import annotations

import json
import sqlite3
import threading

import numpy as np
import pytest

from nprt.service.checkpoint import clear_checkpoint, load_checkpoint, save_checkpoint
from nprt.service.store import JobStore, add_columns


def test_store_uses_wal_and_lists_unfinished_oldest_first(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    for i in range(4):
        store.insert(f"job{i}", "forest:tiny", {"spp": i}, passes_total=8)
    assert store.finish("job1", "succeeded", stats={"rays": {"primary": 3}}) == "succeeded"
    assert store.transition("job2", "running", ("queued",), passes_done=5)
    assert [r.id for r in store.unfinished()] == ["job0", "job2", "job3"]
    page, total = store.list(offset=0, limit=2)
    assert [r.id for r in page] == ["job3", "job2"] and total == 4
    assert store.get("job2").progress == 5 / 8
    assert store.get("job1").stats == {"rays": {"primary": 3}}
    store.close()
    db = sqlite3.connect(tmp_path / "jobs.sqlite3")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_store_refuses_unknown_state_and_columns(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    store.insert("a", "forest", {}, 1)
    with pytest.raises(ValueError, match="unknown job state 'done'"):
        store.transition("a", "done", ("queued",))
    with pytest.raises(ValueError, match=r"not updatable job fields: \['scene'\]"):
        store.update("a", scene="city")
    with pytest.raises(ValueError, match=r"not updatable job fields: \['state'\]"):
        store.update("a", state="running")
    with pytest.raises(ValueError, match="terminal states are entered through finish"):
        store.transition("a", "succeeded", ("running",))


def test_terminal_states_are_final(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    store.insert("a", "forest", {}, 4)
    assert store.transition("a", "running", ("queued",))
    assert store.finish("a", "succeeded", passes_done=4) == "succeeded"
    before = store.get("a")
    assert not store.transition("a", "queued", ("queued", "preparing", "running"))
    assert store.finish("a", "canceled") is None and store.finish("a", "failed") is None
    assert not store.request_cancel("a") and not store.requeue("a", max_retries=5)
    assert not store.update("a", passes_done=1, error="late")
    assert store.get("a") == before


def test_stored_cancel_wins_over_a_late_success_but_not_over_a_failure(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    for job in ("queued", "ok", "bad"):
        store.insert(job, "forest", {}, 4)
    for job in ("ok", "bad"):
        store.transition(job, "running", ("queued",))
    assert all(store.request_cancel(j) for j in ("queued", "ok", "bad"))
    assert store.get("queued").state == "canceled" and store.get("queued").finished_at
    assert store.get("ok").state == "running" and store.get("ok").cancel_requested
    assert store.finish("ok", "succeeded") == "canceled"
    assert store.finish("bad", "failed", error="boom") == "failed"
    assert [r.id for r in store.unfinished()] == []


def test_cancel_racing_completion_never_leaves_a_terminal_state(tmp_path):
    """A render thread finishing and a client cancelling at the same moment, many times:
    whoever loses changes nothing, and an accepted cancel always ends canceled."""
    store = JobStore(tmp_path / "jobs.sqlite3")
    outcomes = {}
    for i in range(300):
        job = f"job{i}"
        store.insert(job, "forest", {}, 1)
        if i % 3:  # a third race a queued job, the rest a running one
            store.transition(job, "preparing", ("queued",))
            store.transition(job, "running", ("preparing",))
        go = threading.Barrier(2)
        got = {}

        def finish(job=job, go=go, got=got):
            go.wait()
            got["finish"] = store.finish(job, "succeeded", passes_done=1)

        def cancel(job=job, go=go, got=got):
            go.wait()
            got["cancel"] = store.request_cancel(job)

        # The thread that reaches the barrier last tends to run first: alternate them.
        threads = [threading.Thread(target=f) for f in ((finish, cancel), (cancel, finish))[i % 2]]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        final = store.get(job)
        assert final.state in ("succeeded", "canceled")
        assert (final.state == "canceled") == got["cancel"], (job, got, final.state)
        # Whichever terminal state came first stays: later calls change nothing.
        assert store.finish(job, "failed") is None and not store.request_cancel(job)
        assert store.get(job).state == final.state
        outcomes[final.state] = outcomes.get(final.state, 0) + 1
    assert set(outcomes) == {"succeeded", "canceled"}, outcomes


def test_requeue_counts_retries_up_to_the_limit(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    store.insert("a", "forest", {}, 4)
    for retry in (1, 2):
        assert store.transition("a", "running", ("queued",))
        assert store.requeue("a", max_retries=2, passes_done=3)
        rec = store.get("a")
        assert (rec.state, rec.retries, rec.passes_done) == ("queued", retry, 3)
    store.transition("a", "running", ("queued",))
    assert not store.requeue("a", max_retries=2) and store.get("a").state == "running"


def test_idempotency_key_returns_the_stored_job(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    first = store.insert("a", "forest", {"spp": 1}, 4, idempotency_key="k1")
    again = store.insert("b", "city", {"spp": 2}, 8, idempotency_key="k1")
    assert again == first and again.idempotency_key == "k1"
    assert store.insert("c", "forest", {}, 1, idempotency_key="k2").id == "c"
    assert store.insert("d", "forest", {}, 1).id == "d"
    assert store.insert("e", "forest", {}, 1).id == "e"  # no key: never deduplicated
    assert store.get("b") is None and store.list()[1] == 4


def test_database_of_an_older_service_gains_the_new_columns(tmp_path):
    path = tmp_path / "jobs.sqlite3"
    old = sqlite3.connect(path)
    old.executescript("""CREATE TABLE jobs (seq INTEGER PRIMARY KEY AUTOINCREMENT,
        id TEXT NOT NULL UNIQUE, scene TEXT NOT NULL, settings TEXT NOT NULL,
        state TEXT NOT NULL, created_at REAL NOT NULL, started_at REAL, finished_at REAL,
        passes_done INTEGER NOT NULL DEFAULT 0, passes_total INTEGER NOT NULL DEFAULT 0,
        error TEXT, stats TEXT, pixel_samples TEXT);
        INSERT INTO jobs (id, scene, settings, state, created_at) VALUES
        ('old', 'forest', '{}', 'running', 1.0);""")
    old.close()
    store = JobStore(path)
    rec = store.get("old")
    assert (rec.cancel_requested, rec.retries, rec.idempotency_key) == (False, 0, None)
    assert store.request_cancel("old") and store.get("old").cancel_requested


def test_a_process_that_read_the_columns_before_another_added_them_opens_the_store(
        tmp_path):
    """API workers, the gRPC child and the scheduler open one store at once: a process
    whose column list was read before another process added a column must not fail
    (it did: "duplicate column name: idempotency_key", the gRPC child exiting on start)."""
    path = tmp_path / "jobs.sqlite3"
    JobStore(path).close()  # every column there now
    db = sqlite3.connect(path, isolation_level=None)
    add_columns(db, have={"seq", "id"})  # as read before the other process's ALTERs
    cols = [r[1] for r in db.execute("PRAGMA table_info(jobs)")]
    assert len(cols) == len(set(cols)) and "idempotency_key" in cols
    with pytest.raises(sqlite3.OperationalError, match="no such table"):
        add_columns(sqlite3.connect(tmp_path / "empty.sqlite3"), have=set())


def test_checkpoint_round_trips_and_keeps_only_the_latest_pair(tmp_path):
    sums = np.random.default_rng(0).random((12, 3))
    samples = np.arange(12, dtype=np.int64)
    save_checkpoint(tmp_path, 3, sums * 0.5, samples, {"rays": {"primary": 1}})
    save_checkpoint(tmp_path, 4, sums, samples + 1, {"rays": {"primary": 2}})
    ck = load_checkpoint(tmp_path)
    assert ck.next_pass == 4 and ck.stats == {"rays": {"primary": 2}}
    np.testing.assert_array_equal(ck.sums, sums)
    np.testing.assert_array_equal(ck.samples, samples + 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "checkpoint.json", "samples-4-0.npy", "sums-4-0.npy"]
    clear_checkpoint(tmp_path)
    assert load_checkpoint(tmp_path) is None and list(tmp_path.iterdir()) == []


def test_checkpoint_json_is_the_commit_point(tmp_path):
    """A crash after the arrays of pass 5 but before its json still resumes at pass 4."""
    save_checkpoint(tmp_path, 4, np.ones((2, 3)), np.ones(2, np.int64), {})
    np.save(tmp_path / "sums-5.npy", np.full((2, 3), 9.0))  # as if killed mid-save
    ck = load_checkpoint(tmp_path)
    assert ck.next_pass == 4 and (ck.sums == 1.0).all()
    assert json.loads((tmp_path / "checkpoint.json").read_text())["next_pass"] == 4


def test_checkpoint_keeps_the_passes_finished_out_of_order(tmp_path):
    save_checkpoint(tmp_path, 4, np.ones((2, 3)), np.ones(2, np.int64), {}, done=[7, 5])
    ck = load_checkpoint(tmp_path)
    assert (ck.next_pass, ck.done) == (4, [5, 7])
