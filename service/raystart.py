"""Starting or joining Ray once for the scheduler process, retrying a failed start. A
Coordinator that started Ray itself would shut it down when its job ends, under any other
sharded job, and every job would pay the start-up again.

A Ray started here belongs to a thread of its own (`nprt-ray`) that lives until shutdown():
Ray's processes die with the thread that forked them (their parent-death signal is per
thread), so a job thread that started Ray and then ended would take Ray from under the jobs
after it, and a raylet killed that way leaves its dashboard and runtime-env agents behind.
shutdown() stops Ray on that thread (the raylet is asked first, so it ends its agents), waits
for the processes to exit, and joins the thread."""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future

log = logging.getLogger(__name__)

RAY_RETRY_S = 2.0  # back-off between tries at starting Ray, times the attempt number


class RayUnavailable(RuntimeError):
    """Starting or joining Ray failed every attempt; the message names the address."""


class RayStarter:
    def __init__(self, address: str | None, attempts: int):
        self.address, self.attempts = address, attempts
        self.started = False  # this process started (not joined) Ray: it shuts it down
        self._lock = threading.Lock()
        self._owner: threading.Thread | None = None
        self._release = threading.Event()  # tells the owner thread to stop Ray and end

    def ensure(self) -> None:
        """Start or join Ray unless done already; RayUnavailable after every attempt."""
        import ray

        with self._lock:
            if self.started or ray.is_initialized():
                return
            ready: Future = Future()
            self._release.clear()
            self._owner = threading.Thread(target=self._own, args=(ready,), name="nprt-ray",
                                           daemon=True)
            self._owner.start()
            try:
                self.started = ready.result()
            finally:
                if not self.started:  # joined, or failed: the thread has nothing to keep
                    self._owner.join()
                    self._owner = None

    def _own(self, ready: Future) -> None:
        """Start or join Ray (with retries) and report to `ready`; keep a Ray started here
        until shutdown() releases it."""
        import ray

        from nprt.workers.runtime import raysession

        address, attempts = self.address, self.attempts
        for attempt in range(1, attempts + 1):
            try:
                started = raysession.ensure_ray(address)
            except Exception as e:
                error = e
                log.warning("starting Ray (%s) failed, attempt %d of %d: %s",
                            address or "local", attempt, attempts, e)
                ray.shutdown()  # a half-made connection would make the next try a no-op
                if attempt < attempts:
                    time.sleep(RAY_RETRY_S * attempt)
                continue
            if started:
                where = f"joined Ray at {address}" if address else "started a local Ray"
                log.info("%s for this scheduler", where)
            ready.set_result(started)
            if started:
                self._release.wait()
                ray.shutdown(wait_for_processes=True)
            return
        where = f"join the Ray cluster at {address}" if address else "start a local Ray"
        failure = RayUnavailable(f"could not {where} in {attempts} attempts: "
                                 f"{type(error).__name__}: {error}")
        failure.__cause__ = error
        ready.set_exception(failure)

    def shutdown(self) -> None:
        """Stop a Ray this process started (its processes included) and end its thread."""
        with self._lock:
            owner, self._owner = self._owner, None
            self.started = False
            if owner is not None:
                self._release.set()
                owner.join()
