"""The API worker's store writer: admissions queued while it works share one commit, and
each still gets its own answer."""

from __future__ import annotations

import asyncio
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
