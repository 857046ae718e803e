"""The API worker's store writer: admissions queued while it works share one commit, each
still gets its own answer, an idempotency key names one job across workers, and a batch
that fails is stored not at all."""

from __future__ import annotations

import asyncio
import sqlite3
import threading

from nprt.service.store import JobStore, QueueFull
from nprt.service.storewriter import StoreWriter


def test_queued_admissions_share_one_commit_and_only_the_overflow_is_refused(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    writer = StoreWriter(store)
    statements: list[str] = []
    store._db.set_trace_callback(statements.append)
    gate = threading.Event()

    async def main():
        held = asyncio.ensure_future(writer.call(gate.wait))  # the writer is busy
        await asyncio.sleep(0)
        rows = [(f"job{i}", "forest:tiny", {}, 1, f"key{i % 5}", None, 4) for i in range(7)]
        burst = [asyncio.ensure_future(writer.insert(*row)) for row in rows]
        await asyncio.sleep(0)  # every insert queued behind the held call
        gate.set()
        await held
        return await asyncio.gather(*burst, return_exceptions=True)

    outs = asyncio.run(main())
    writer.stop()
    # key0..key3 stored; key4 is past the depth of 4; job5, job6 replay key0, key1.
    assert [o.id for o in outs[:4]] == ["job0", "job1", "job2", "job3"]
    assert isinstance(outs[4], QueueFull) and "4 jobs are queued" in str(outs[4])
    assert [o.id for o in outs[5:]] == ["job0", "job1"]
    assert sum(s == "COMMIT" for s in statements) == 1
    assert store.counts_by_state()["queued"] == 4


def test_a_failing_call_answers_its_caller_and_the_writer_goes_on(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    writer = StoreWriter(store)

    def boom():
        raise ValueError("bad write")

    async def main():
        failed = await asyncio.gather(writer.call(boom), return_exceptions=True)
        return failed[0], await writer.insert("a", "forest:tiny", {}, 1, None, None, None)

    error, rec = asyncio.run(main())
    writer.stop()
    assert isinstance(error, ValueError) and str(error) == "bad write"
    assert rec.id == "a" and store.get("a").state == "queued"


def test_two_workers_admitting_the_same_keys_at_once_store_each_key_once(tmp_path):
    """Two API workers (a writer and a connection each) take a burst whose keys repeat
    within and across them: every answer for a key names one job, and that job is stored,
    once."""
    writers = [StoreWriter(JobStore(tmp_path / "jobs.sqlite3")) for _ in range(2)]
    n, keys = 240, 39  # odd: the rows of a key alternate between the workers

    async def main():
        burst = [asyncio.ensure_future(writers[i % 2].insert(
            f"job{i}", "forest:tiny", "{}", 1, f"key{i % keys}", None, None)) for i in range(n)]
        return await asyncio.gather(*burst)

    outs = asyncio.run(main())
    for w in writers:
        w.stop()
    by_key: dict[str, set[str]] = {}
    for i, rec in enumerate(outs):
        by_key.setdefault(f"key{i % keys}", set()).add(rec.id)
    assert all(len(ids) == 1 for ids in by_key.values())
    stored, total = JobStore(tmp_path / "jobs.sqlite3").list(limit=n)
    assert total == keys
    assert {r.idempotency_key: r.id for r in stored} == \
        {k: next(iter(ids)) for k, ids in by_key.items()}


def test_a_batch_whose_transaction_fails_answers_every_caller_and_stores_none_of_it(tmp_path):
    """One row of a batch breaks its transaction (an id stored already): each admission of
    the batch gets the error, none of them is stored (none was answered as accepted), and
    the same requests sent again are stored once each."""
    store = JobStore(tmp_path / "jobs.sqlite3")
    store.insert("taken", "forest:tiny", "{}", 1)
    writer = StoreWriter(store)
    gate = threading.Event()
    rows = [(f"job{i}", "forest:tiny", "{}", 1, f"key{i}", None, None) for i in range(6)]

    async def burst(rows):
        held = asyncio.ensure_future(writer.call(gate.wait))  # the writer is busy
        await asyncio.sleep(0)
        queued = [asyncio.ensure_future(writer.insert(*row)) for row in rows]
        await asyncio.sleep(0)  # every insert queued behind the held call: one batch
        gate.set()
        await held
        return await asyncio.gather(*queued, return_exceptions=True)

    broken = rows[:3] + [("taken", "forest:tiny", "{}", 1, "key-x", None, None)] + rows[3:]
    outs = asyncio.run(burst(broken))
    assert all(isinstance(o, sqlite3.IntegrityError) for o in outs)
    assert store.list()[1] == 1  # only the job stored before
    gate.clear()
    again = asyncio.run(burst(rows + rows))  # retried, each twice
    writer.stop()
    assert [o.id for o in again] == [r[0] for r in rows] * 2
    assert store.list()[1] == 1 + len(rows)
