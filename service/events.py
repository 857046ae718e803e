"""Per-job event fan-out from the event feed (nprt.service.feed) to SSE streams and gRPC
watchers.

Each watcher holds a Subscription: state events queue in order and are never dropped (a
job has a handful); tiles queue in order too, bounded in bytes: past the bound, a tile that
a newer pending tile of the same rectangle supersedes goes first (the newer one holds every
sample so far), then the oldest. A watcher that keeps up gets every tile, even when the
feed hands over a burst of them at once; a slow one costs bounded memory and gets the
latest image rather than every tile.

Fan-out cost is paid once per event, not once per watcher, where it can be: `encoded`
keeps an event's wire form (SSE text, gRPC message) for every watcher of the process, and
the watchers on one event loop are woken with one cross-thread call per batch.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable

from nprt.service.errors import TooManyWatchers

log = logging.getLogger(__name__)

Notify = Callable[[], None]


def _tile_bytes(event: dict) -> int:
    rgb = event.get("rgb")
    return 0 if rgb is None else int(rgb.nbytes)


class Subscription:
    """One watcher's pending events. put() runs on the feed's thread, drain() on the
    watcher's; notify() is called after every put, outside the lock."""

    def __init__(self, notify: Notify, max_tile_bytes: int, on_close: Callable[[], None]):
        self._lock = threading.Lock()
        # (kind, seq) -> event, in arrival order; _latest: rect -> key of its newest tile.
        self._pending: OrderedDict[tuple, dict] = OrderedDict()
        self._latest: dict[tuple, tuple] = {}
        self._pending_tile_bytes = 0
        self._seq = itertools.count()
        self._notify = notify
        self._on_close = on_close
        self.max_tile_bytes = max_tile_bytes
        self.coalesced_tiles = 0  # evicted for a newer pending tile of the same rect
        self.dropped_tiles = 0  # evicted, the newest of its rect, over max_tile_bytes

    def put(self, event: dict) -> None:
        with self._lock:
            if event["type"] == "tile":
                key = ("tile", next(self._seq))
                self._pending[key] = event
                self._latest[tuple(event["rect"])] = key
                self._pending_tile_bytes += _tile_bytes(event)
                self._evict_tiles(keep=key)
            else:
                self._pending[("state", next(self._seq))] = event
        self._notify()

    def _evict_tiles(self, keep: tuple) -> None:
        """While over the byte bound, drop superseded tiles (oldest first), then the
        oldest tiles; never the newest."""
        if self._pending_tile_bytes <= self.max_tile_bytes:
            return
        for superseded in (True, False):
            for key in [k for k in self._pending if k[0] == "tile" and k != keep]:
                rect = tuple(self._pending[key]["rect"])
                if superseded and self._latest.get(rect) == key:
                    continue
                self._pending_tile_bytes -= _tile_bytes(self._pending.pop(key))
                if self._latest.get(rect) == key:
                    del self._latest[rect]
                    self.dropped_tiles += 1
                else:
                    self.coalesced_tiles += 1
                if self._pending_tile_bytes <= self.max_tile_bytes:
                    return

    def drain(self) -> list[dict]:
        """Every pending event, oldest first."""
        with self._lock:
            out = list(self._pending.values())
            self._pending.clear()
            self._latest.clear()
            self._pending_tile_bytes = 0
        return out

    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    def close(self) -> None:
        self._on_close()


class EventBroker:
    """Subscriptions by job id, and the bound on how many are open at once."""

    def __init__(self, max_watchers: int = 1_000, max_tile_bytes: int = 8 << 20):
        self._lock = threading.Lock()
        self._subs: dict[str, list[Subscription]] = {}
        self.max_watchers = max_watchers
        self.max_tile_bytes = max_tile_bytes

    def check_capacity(self) -> None:
        """TooManyWatchers when max_watchers are open."""
        with self._lock:
            self._check_capacity()

    def _check_capacity(self) -> None:
        total = sum(len(s) for s in self._subs.values())
        if total >= self.max_watchers:
            raise TooManyWatchers(f"{total} event streams are open, the limit "
                                  "(NPRT_MAX_WATCHERS); try again later")

    def subscribe(self, job_id: str, notify: Notify) -> Subscription:
        """Start collecting `job_id`'s events; TooManyWatchers beyond max_watchers in all."""
        with self._lock:
            self._check_capacity()
            sub = Subscription(notify, self.max_tile_bytes,
                               on_close=lambda: self._unsubscribe(job_id, sub))
            self._subs.setdefault(job_id, []).append(sub)
        return sub

    def _unsubscribe(self, job_id: str, sub: Subscription) -> None:
        with self._lock:
            subs = self._subs.get(job_id, [])
            if sub in subs:
                subs.remove(sub)
            if not subs:
                self._subs.pop(job_id, None)

    def publish(self, job_id: str, event: dict) -> None:
        """Hand `event` to every watcher of `job_id` (a failing one is logged, skipped)."""
        with self._lock:
            subs = list(self._subs.get(job_id, ()))
        for sub in subs:
            try:
                sub.put(event)
            except Exception:  # one broken watcher must not stop the others
                log.exception("event subscriber for job %s failed", job_id)

    def subscribers(self, job_id: str) -> int:
        with self._lock:
            return len(self._subs.get(job_id, ()))


def encoded(event: dict, key, encode: Callable[[dict], object]):
    """encode(event), computed once per event and key for all the watchers that get it (a
    race on two threads at worst encodes twice)."""
    cache = event.setdefault("_encoded", {})
    if key not in cache:
        cache[key] = encode(event)
    return cache[key]


class _LoopWaker:
    """Sets the asyncio.Events of many watchers on one loop from another thread with one
    call_soon_threadsafe (one write to the loop's wake-up pipe) per batch."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        self._loop = loop
        self._lock = threading.Lock()
        self._due: set[asyncio.Event] = set()

    def wake(self, event: asyncio.Event) -> None:
        with self._lock:
            first = not self._due
            self._due.add(event)
        if first:
            try:
                self._loop.call_soon_threadsafe(self._flush)
            except RuntimeError:  # the loop closed under a late event
                pass

    def _flush(self) -> None:
        with self._lock:
            due, self._due = self._due, set()
        for event in due:
            event.set()


_wakers: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_wakers_lock = threading.Lock()


def _waker(loop: asyncio.AbstractEventLoop) -> _LoopWaker:
    with _wakers_lock:
        waker = _wakers.get(loop)
        if waker is None:
            waker = _wakers[loop] = _LoopWaker(loop)
        return waker


class AsyncWatch:
    """A Subscription for a coroutine on the running loop (SSE, grpc.aio): no thread is
    held while it waits. Use as an async context manager."""

    def __init__(self, subscribe: Callable[[Notify], Subscription]):
        self._wake = asyncio.Event()
        waker = _waker(asyncio.get_running_loop())
        self.sub = subscribe(lambda: waker.wake(self._wake))

    async def next_events(self) -> list[dict]:
        """The pending events, waiting for at least one."""
        while not (events := self.sub.drain()):
            await self._wake.wait()
            self._wake.clear()
        return events

    async def __aenter__(self) -> AsyncWatch:
        return self

    async def __aexit__(self, *exc) -> None:
        self.sub.close()
