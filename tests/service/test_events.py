"""Subscriber queues: state events are never dropped, tiles are bounded in bytes (past the
bound superseded tiles of a rectangle go first), and the number of open watchers is
capped."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from nprt.service.errors import TooManyWatchers
from nprt.service.events import AsyncWatch, EventBroker


def _tile(rect, value: float, edge: int = 16) -> dict:
    return {"type": "tile", "rect": rect, "pass_index": int(value),
            "rgb": np.full((edge, edge, 3), value, np.float32)}


def _state(name: str) -> dict:
    return {"type": "state", "job": name}


def test_slow_watcher_gets_every_state_and_the_latest_tile_of_each_rect():
    tile_bytes = 16 * 16 * 3 * 4
    broker = EventBroker(max_tile_bytes=2 * tile_bytes)
    sub = broker.subscribe("j", lambda: None)
    broker.publish("j", _state("running"))
    rects = [(0, 0, 16, 16), (16, 0, 32, 16)]
    for sample in range(50):  # 50 sample chunks over two tiles, nobody reading
        for rect in rects:
            broker.publish("j", _tile(rect, sample))
    broker.publish("j", _state("succeeded"))
    events = sub.drain()
    assert [e["type"] for e in events] == ["state", "tile", "tile", "state"]
    assert [e["job"] for e in events if e["type"] == "state"] == ["running", "succeeded"]
    latest = {tuple(e["rect"]): e["rgb"][0, 0, 0] for e in events if e["type"] == "tile"}
    assert latest == {rects[0]: 49.0, rects[1]: 49.0}
    assert sub.coalesced_tiles == 98 and sub.dropped_tiles == 0
    assert sub.drain() == []


def test_watcher_under_the_bound_gets_every_tile_of_a_burst_in_order():
    broker = EventBroker()
    sub = broker.subscribe("j", lambda: None)
    for sample in range(3):  # one feed poll hands over three passes of one rect at once
        broker.publish("j", _tile((0, 0, 16, 16), sample))
    assert [e["pass_index"] for e in sub.drain()] == [0, 1, 2]
    assert sub.coalesced_tiles == sub.dropped_tiles == 0


def test_pending_tiles_are_bounded_in_bytes_and_states_are_never_dropped():
    tile_bytes = 16 * 16 * 3 * 4
    broker = EventBroker(max_tile_bytes=3 * tile_bytes)
    sub = broker.subscribe("j", lambda: None)
    for i in range(1000):
        broker.publish("j", _tile((16 * i, 0, 16 * i + 16, 16), i))
        broker.publish("j", _state(f"s{i}"))
    events = sub.drain()
    tiles = [e["pass_index"] for e in events if e["type"] == "tile"]
    assert tiles == [997, 998, 999]  # the newest ones
    assert [e["job"] for e in events if e["type"] == "state"] == [f"s{i}" for i in range(1000)]
    assert sub.dropped_tiles == 997


def test_one_tile_over_the_bound_is_still_delivered():
    broker = EventBroker(max_tile_bytes=10)
    sub = broker.subscribe("j", lambda: None)
    broker.publish("j", _tile((0, 0, 16, 16), 1))
    broker.publish("j", _tile((16, 0, 32, 16), 2))
    assert [e["pass_index"] for e in sub.drain()] == [2]


def test_watchers_over_the_limit_are_refused_until_one_closes():
    broker = EventBroker(max_watchers=2)
    a = broker.subscribe("j", lambda: None)
    broker.subscribe("k", lambda: None)
    with pytest.raises(TooManyWatchers, match="2 event streams are open"):
        broker.subscribe("j", lambda: None)
    with pytest.raises(TooManyWatchers):
        broker.check_capacity()
    a.close()
    broker.subscribe("j", lambda: None)
    assert broker.subscribers("j") == 1 and broker.subscribers("k") == 1


def test_a_failing_watcher_does_not_stop_the_others():
    broker = EventBroker()

    def boom():
        raise RuntimeError("watcher gone")

    broker.subscribe("j", boom)
    ok = broker.subscribe("j", lambda: None)
    broker.publish("j", _state("running"))
    assert [e["job"] for e in ok.drain()] == ["running"]


def test_async_watch_wakes_on_events_from_another_thread():
    broker = EventBroker()

    async def main():
        async with AsyncWatch(lambda notify: broker.subscribe("j", notify)) as watch:
            publisher = threading.Thread(target=lambda: [
                broker.publish("j", _state(s)) for s in ("preparing", "running")])
            publisher.start()
            got = []
            while len(got) < 2:
                got += [e["job"] for e in await asyncio.wait_for(watch.next_events(), 30)]
            publisher.join()
            return got

    assert asyncio.run(main()) == ["preparing", "running"]
    assert broker.subscribers("j") == 0  # closed on exit
