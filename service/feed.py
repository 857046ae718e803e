"""The notification channel on the API side: one thread per API process reads the events
table in order (state snapshots and tiles appended by the scheduler or by another API
worker) and hands each to this process's watchers through the EventBroker. Any API worker
can so serve any watcher, and a render never runs where the watchers are served."""

from __future__ import annotations

import json
import logging
import threading

import numpy as np

from nprt.service.events import EventBroker
from nprt.service.store import JobStore, record_from_json

log = logging.getLogger(__name__)

FEED_POLL_S = 0.05  # how long an event waits at most before a watcher hears of it
FEED_BATCH = 1000  # events read per query


class EventFeed:
    """Polls `store` for events after the newest one present at start and publishes them
    to `broker` (a tile as {"type": "tile", ..., "rgb": (h, w, 3) float32})."""

    def __init__(self, store: JobStore, broker: EventBroker, poll_s: float = FEED_POLL_S):
        self.store, self.broker, self.poll_s = store, broker, poll_s
        self._seq = store.max_event_seq()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="nprt-event-feed", daemon=True)

    def start(self) -> EventFeed:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()  # a poll is one bounded read; then it sees the stop

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                n = self.poll()
            except Exception:  # the store may be briefly busy; the next poll catches up
                log.exception("reading job events failed")
                n = 0
            if n < FEED_BATCH:
                self._stop.wait(self.poll_s)

    def poll(self) -> int:
        """Publish the events stored since the last poll; returns how many there were."""
        rows = self.store.events_after(self._seq, FEED_BATCH)
        for seq, job_id, kind, body, rgb in rows:
            self._seq = seq
            if not self.broker.subscribers(job_id):
                continue
            self.broker.publish(job_id, _event(kind, body, rgb))
        return len(rows)


def _event(kind: str, body: str, rgb: bytes | None) -> dict:
    if kind == "state":
        return {"type": "state", "job": record_from_json(body)}
    tile = json.loads(body)
    x0, y0, x1, y1 = tile["rect"]
    tile["rect"] = (x0, y0, x1, y1)
    tile["rgb"] = np.frombuffer(rgb, np.float32).reshape(y1 - y0, x1 - x0, 3)
    return {"type": "tile", **tile}
