"""Per-job event fan-out from render threads to SSE streams and gRPC watchers.

Subscribers are plain callables; each adapter decides how to hop threads (an asyncio
loop's call_soon_threadsafe, or a queue.Queue's put).
"""

from __future__ import annotations

import logging
import threading
from collections import defaultdict
from collections.abc import Callable

log = logging.getLogger(__name__)

Deliver = Callable[[dict], None]


class EventBroker:
    def __init__(self):
        self._lock = threading.Lock()
        self._subs: dict[str, list[Deliver]] = defaultdict(list)

    def subscribe(self, job_id: str, deliver: Deliver) -> Callable[[], None]:
        """Start delivering `job_id`'s events; returns the unsubscribe function."""
        with self._lock:
            self._subs[job_id].append(deliver)

        def unsubscribe() -> None:
            with self._lock:
                subs = self._subs.get(job_id, [])
                if deliver in subs:
                    subs.remove(deliver)
                if not subs:
                    self._subs.pop(job_id, None)

        return unsubscribe

    def publish(self, job_id: str, event: dict) -> None:
        with self._lock:
            subs = list(self._subs.get(job_id, ()))
        for deliver in subs:
            try:
                deliver(event)
            except Exception:  # one broken subscriber must not stop a render
                log.exception("event subscriber for job %s failed", job_id)

    def subscribers(self, job_id: str) -> int:
        with self._lock:
            return len(self._subs.get(job_id, ()))
