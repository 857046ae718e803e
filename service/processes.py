"""Which process owns what, and how `nprt serve` starts them.

- **API workers** (`nprt serve --api-only`, or each of `nprt serve --workers N`): the
  FastAPI app. They validate, store and read jobs in the SQLite store, read images from
  the job folders, and serve SSE watchers from the store's events table
  (nprt.service.feed). They never render, start Ray or hold a film; several can run on one
  data directory. Inside one: HTTP on uvicorn's uvloop loop (the polled reads and
  admissions answered before FastAPI routing: fastreads, admission), one thread polling
  the store's events for every watcher (feed), and one thread for the store's writes,
  which batches the admissions of a burst into one commit (storewriter).
- **The gRPC server** (`nprt grpc`, or the child process `nprt serve` starts before its
  HTTP workers answer): an API worker for gRPC alone, with its own feed and writer
  threads, so that neither its tile fan-out and health checks nor a burst of HTTP requests
  wait for the other's interpreter lock (grpc_child). `create_app(grpc_port=...)` still
  runs it on a thread of an HTTP worker instead (tests, embedding).
- **The scheduler** (`nprt scheduler`, or the child process `nprt serve` starts): Ray and
  the warm shard pools, the queue, the job slots, the state machine, the checkpoints, and
  every render (the single-process reference included). One per data directory (a lock
  file), restartable at any time: unfinished jobs resume from their checkpoints. A Ray it
  starts belongs to one thread (raystart), and stopping the scheduler stops that Ray, its
  agents included, and joins every thread it started. It and all it starts run below the
  API on the CPU: SCHED_IDLE in the API's session by default (priority).
- **The store** (`<data_dir>/jobs.sqlite3`, WAL): the shared truth. Jobs, their states
  (compare-and-set), idempotency keys (a unique index: exactly-once admission across
  workers), and the events (state snapshots and tiles) that carry notifications.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time

from nprt.service.config import ServiceSettings
from nprt.service.priority import yield_cpu

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1


def run_scheduler(settings: ServiceSettings) -> int:
    """Run a scheduler in this process until SIGTERM or SIGINT, then stop it (renders stop
    at their next pass boundary and resume on the next start)."""
    from nprt.service.scheduler import Scheduler, SchedulerRunning

    yield_cpu(settings.scheduler_cpu, settings.scheduler_nice,
              settings.scheduler_own_session, settings.scheduler_session_nice)
    done = threading.Event()
    scheduler = Scheduler(settings)

    def on_signal(*_) -> None:
        done.set()
        scheduler.interrupt()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    try:
        scheduler.start()
    except SchedulerRunning as e:
        log.error("%s", e)
        scheduler.store.close()
        return 1
    try:
        done.wait()
    finally:
        scheduler.stop()
        log.info("scheduler stopped; unfinished jobs resume on the next start")
    return 0


def _die_with_parent() -> None:
    """In the child, before exec: SIGKILL when the parent dies (Linux), so a killed
    `nprt serve` leaves no scheduler holding the data directory (its jobs resume from their
    checkpoints, as after any crash). A parent that exits normally stops it with SIGTERM."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except OSError:
        pass


def spawn_child(settings: ServiceSettings, command: list[str]) -> subprocess.Popen:
    """`nprt <command>` as a child process on the same settings (passed as NPRT_*)."""
    env = {**os.environ}
    for name, value in settings.model_dump(exclude_none=True).items():
        env[f"NPRT_{name.upper()}"] = str(value)
    cmd = [sys.executable, "-m", "nprt.service", *command]
    return subprocess.Popen(cmd, env=env, preexec_fn=_die_with_parent)


def spawn_scheduler(settings: ServiceSettings, log_args: list[str]) -> subprocess.Popen:
    """`nprt scheduler` as a child process on the same settings."""
    return spawn_child(settings, ["scheduler", *log_args])


class ChildProcess:
    """A child of `nprt serve`, started again whenever it exits (a crash, an OOM kill):
    the scheduler's jobs resume from their checkpoints, gRPC clients reconnect, and REST
    never stops answering. Restarts back off from RESPAWN_S up to RESPAWN_MAX_S while it
    keeps failing fast."""

    RESPAWN_S = 1.0
    RESPAWN_MAX_S = 60.0
    HEALTHY_S = 30.0  # a run this long resets the back-off

    def __init__(self, name: str, spawn):
        self.name, self._spawn = name, spawn
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.proc = self._spawn()
        self._thread = threading.Thread(target=self._watch, name=f"nprt-{name}-watch",
                                        daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        delay = self.RESPAWN_S
        while not self._stop.is_set():
            started = time.monotonic()
            code = self.proc.wait()
            if self._stop.is_set():
                return
            delay = self.RESPAWN_S if time.monotonic() - started > self.HEALTHY_S else delay
            log.error("the %s (pid %d) exited with %s; starting it again in %.0f s",
                      self.name, self.proc.pid, code, delay)
            if self._stop.wait(delay):
                return
            with self._lock:
                if not self._stop.is_set():
                    self.proc = self._spawn()
            delay = min(2 * delay, self.RESPAWN_MAX_S)

    def stop(self, timeout_s: float = 30.0) -> None:
        with self._lock:
            self._stop.set()
        stop_child(self.proc, timeout_s, self.name)
        self._thread.join()


class SchedulerChild(ChildProcess):
    """The scheduler child of `nprt serve`."""

    def __init__(self, settings: ServiceSettings, log_args: list[str]):
        super().__init__("scheduler", lambda: spawn_scheduler(settings, log_args))


def stop_child(proc: subprocess.Popen, timeout_s: float = 30.0, name: str = "scheduler"
               ) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("%s %d did not stop in %.0f s; killing it", name, proc.pid, timeout_s)
            proc.kill()
            proc.wait()
