"""The SQLite job store and the per-pass checkpoint files."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from service.checkpoint import clear_checkpoint, load_checkpoint, save_checkpoint
from service.store import JobStore


def test_store_uses_wal_and_lists_unfinished_oldest_first(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    for i in range(4):
        store.insert(f"job{i}", "forest:tiny", {"spp": i}, passes_total=8)
    store.update("job1", state="succeeded", stats={"rays": {"primary": 3}})
    store.update("job2", state="running", passes_done=5)
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
        store.update("a", state="done")
    with pytest.raises(ValueError, match=r"not updatable job fields: \['scene'\]"):
        store.update("a", scene="city")


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
