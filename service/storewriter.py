"""The store writes of one API worker, on one thread: admissions that queue up while it
works are stored together in one transaction (a burst of 500 costs a few commits, not 500),
and the coroutines waiting on one batch are woken with one call per event loop. A write
may wait for another process's, so none runs on an event loop."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from itertools import groupby

from nprt.service.store import JobRecord, JobStore, QueueFull

_INSERT = object()  # marks a queued insert row (batched), as opposed to a plain call


class StoreWriter:
    def __init__(self, store: JobStore):
        self.store = store
        self._cond = threading.Condition()
        self._queue: list[tuple] = []  # (fn or _INSERT, args, loop, future)
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="nprt-store-writer",
                                        daemon=True)
        self._thread.start()

    async def insert(self, *row) -> JobRecord:
        """JobStore.insert(*row), batched with the inserts queued beside it (QueueFull,
        or sqlite3.OperationalError when another process held the write lock too long)."""
        return await self._put(_INSERT, row)

    async def call(self, fn: Callable, *args):
        """fn(*args) on the writer thread, in turn with the inserts."""
        return await self._put(fn, args)

    async def _put(self, fn, args: tuple):
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        with self._cond:
            if self._closed:
                raise RuntimeError("the store writer is stopped")
            self._queue.append((fn, args, loop, future))
            self._cond.notify()
        return await future

    def stop(self) -> None:
        """Finish what is queued, then end the thread."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join()  # each queued write ends: the store's busy timeout bounds it

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if not self._queue:
                    return
                items, self._queue = self._queue, []
            settled = []  # (loop, future, result, exception)
            for is_insert, run in groupby(items, key=lambda it: it[0] is _INSERT):
                run = list(run)
                settled += self._inserts(run) if is_insert else [self._call(it) for it in run]
            by_loop: dict = {}
            for loop, *rest in settled:
                by_loop.setdefault(loop, []).append(rest)
            for loop, results in by_loop.items():
                try:
                    loop.call_soon_threadsafe(_settle, results)
                except RuntimeError:  # that loop closed; nobody waits any more
                    pass

    def _inserts(self, run: list[tuple]) -> list[tuple]:
        try:
            outs = self.store.insert_many([args for _, args, _, _ in run])
        except Exception as e:  # the whole transaction failed (busy store)
            return [(loop, fut, None, e) for _, _, loop, fut in run]
        return [(loop, fut, None, out) if isinstance(out, QueueFull) else
                (loop, fut, out, None) for (_, _, loop, fut), out in
                zip(run, outs, strict=True)]

    @staticmethod
    def _call(item: tuple) -> tuple:
        fn, args, loop, fut = item
        try:
            return loop, fut, fn(*args), None
        except Exception as e:
            return loop, fut, None, e


def _settle(results: list) -> None:
    for future, result, error in results:
        if future.done():  # its caller was canceled
            continue
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
