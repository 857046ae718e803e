"""Which process owns what, and how `nprt serve` starts them.

- **API workers** (`nprt serve --api-only`, or each of `nprt serve --workers N`): the
  FastAPI app and the gRPC servicer. They validate, store and read jobs in the SQLite
  store, read images from the job folders, and serve watchers from the store's events
  table (nprt.service.feed). They never render, start Ray or hold a film; several can run
  on one data directory (the gRPC port is shared with SO_REUSEPORT).
- **The scheduler** (`nprt scheduler`, or the child process `nprt serve` starts): Ray and
  the warm shard pools, the queue, the job slots, the state machine, the checkpoints, and
  every render (the single-process reference included). One per data directory (a lock
  file), restartable at any time: unfinished jobs resume from their checkpoints.
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

from nprt.service.config import ServiceSettings

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1


def run_scheduler(settings: ServiceSettings) -> int:
    """Run a scheduler in this process until SIGTERM or SIGINT, then stop it (renders stop
    at their next pass boundary and resume on the next start)."""
    from nprt.service.scheduler import Scheduler, SchedulerRunning

    done = threading.Event()
    if settings.scheduler_nice:  # inherited by Ray's processes, which this one starts
        os.nice(settings.scheduler_nice)
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
    return 0


def _die_with_parent() -> None:
    """In the child, before exec: SIGKILL when the parent dies (Linux), so a killed
    `nprt serve` leaves no scheduler holding the data directory (its jobs resume from their
    checkpoints, as after any crash). A parent that exits normally stops it with SIGTERM."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except OSError:
        pass


def spawn_scheduler(settings: ServiceSettings, log_args: list[str]) -> subprocess.Popen:
    """`nprt scheduler` as a child process on the same settings (passed as NPRT_*)."""
    env = {**os.environ}
    for name, value in settings.model_dump(exclude_none=True).items():
        env[f"NPRT_{name.upper()}"] = str(value)
    cmd = [sys.executable, "-m", "nprt.service", "scheduler", *log_args]
    return subprocess.Popen(cmd, env=env, preexec_fn=_die_with_parent)


def stop_child(proc: subprocess.Popen, timeout_s: float = 30.0) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("scheduler %d did not stop in %.0f s; killing it", proc.pid, timeout_s)
            proc.kill()
            proc.wait()
