"""Starting or joining Ray once for the scheduler process, retrying a failed start. A
Coordinator that started Ray itself would shut it down when its job ends, under any other
sharded job, and every job would pay the start-up again."""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger(__name__)

RAY_RETRY_S = 2.0  # back-off between tries at starting Ray, times the attempt number


class RayUnavailable(RuntimeError):
    """Starting or joining Ray failed every attempt; the message names the address."""


class RayStarter:
    def __init__(self, address: str | None, attempts: int):
        self.address, self.attempts = address, attempts
        self.started = False  # this process started (not joined) Ray: it shuts it down
        self._lock = threading.Lock()

    def ensure(self) -> None:
        """Start or join Ray unless done already; RayUnavailable after every attempt."""
        import ray

        from nprt.workers.runtime.raysession import ensure_ray

        address, attempts = self.address, self.attempts
        with self._lock:
            for attempt in range(1, attempts + 1):
                try:
                    if ensure_ray(address):
                        self.started = True
                        where = f"joined Ray at {address}" if address else "started a local Ray"
                        log.info("%s for this scheduler", where)
                    return
                except Exception as e:
                    error = e
                    log.warning("starting Ray (%s) failed, attempt %d of %d: %s",
                                address or "local", attempt, attempts, e)
                    ray.shutdown()  # a half-made connection would make the next try a no-op
                if attempt < attempts:
                    time.sleep(RAY_RETRY_S * attempt)
        where = f"join the Ray cluster at {address}" if address else "start a local Ray"
        raise RayUnavailable(f"could not {where} in {attempts} attempts: "
                             f"{type(error).__name__}: {error}") from error

    def shutdown(self) -> None:
        if self.started:
            import ray

            ray.shutdown()
            self.started = False
