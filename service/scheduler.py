"""The scheduler: the one process that renders. It owns Ray and the warm shard pools, the
queue (jobs stored by any API worker, picked up from the store in order), the job slots,
the job state machine and the checkpoints; on start it re-queues what a previous
scheduler left unfinished. It learns of new jobs and stored cancels by polling the store.

State changes are compare-and-set in the store: a cancel is stored before it is acted on
and wins over a late success, and nothing leaves a terminal state."""

from __future__ import annotations

import fcntl
import logging
import os
import queue
import threading
import time
from pathlib import Path

from nprt.service import checkpoint
from nprt.service.config import ServiceSettings
from nprt.service.joblog import job_log
from nprt.service.jobstates import JobStates
from nprt.service.raystart import RayStarter
from nprt.service.runjob import JobRunner, LiveJob
from nprt.service.scenes import SceneStore
from nprt.service.store import TERMINAL, UNFINISHED, JobStore
from nprt.workers.settings import RenderSettings

log = logging.getLogger(__name__)

POLL_S = 0.05  # how often the store is read for new jobs and stored cancels
SLOT_POLL_S = 0.5  # how often a job waiting for a sharded-job slot looks for its cancel
# Events older than this are pruned; every API worker reads them within a poll (50 ms).
TILE_EVENT_KEEP_S = 10.0  # tiles are the bulk: a 64x64 tile is 48 KiB per pass
STATE_EVENT_KEEP_S = 600.0
PRUNE_EVERY_S = 2.0
LOCK_NAME = "scheduler.lock"
LOCK_WAIT_S = 60.0  # a previous scheduler may still be stopping (checkpointing) when we start


class SchedulerRunning(RuntimeError):
    """Another scheduler holds the data directory's lock."""


class Scheduler:
    def __init__(self, settings: ServiceSettings, scenes: SceneStore | None = None):
        from nprt.workers.runtime.pool import PoolRegistry

        self.settings = settings
        self.scenes = scenes or SceneStore(settings)
        self.store = JobStore(settings.db_path)
        self.states = JobStates(self.store)
        self.ray = RayStarter(settings.ray_address, settings.ray_start_attempts)
        limits = {k: v for k, v in (("max_bytes", settings.pool_max_bytes),
                                    ("max_pools", settings.pool_max_count)) if v is not None}
        self.pools = PoolRegistry(**limits)
        self.runner = JobRunner(self)
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._live: dict[str, LiveJob] = {}
        self._running: set[str] = set()  # jobs a worker holds (waiting for a slot included)
        self._lock = threading.Lock()
        self._idle = threading.Condition(self._lock)
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self._seen_seq = 0
        self._lock_file = None
        # Without placement groups, two Coordinators that each ask for the whole cluster can
        # each get part of their actors and then wait on each other for ever.
        self._sharded_slots = threading.BoundedSemaphore(settings.max_sharded_jobs)
        settings.jobs_dir.mkdir(parents=True, exist_ok=True)

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def interrupt(self) -> None:
        """From a signal handler: stop waiting for the lock; stop() does the rest."""
        self._stopping.set()

    # ------------------------------------------------------------ lifecycle

    def start(self, lock_wait_s: float = LOCK_WAIT_S) -> Scheduler:
        """Take the data directory's lock (SchedulerRunning if another scheduler keeps it
        lock_wait_s), re-queue unfinished jobs, and start the job slots and the store
        poller."""
        self._take_lock(lock_wait_s)
        self._seen_seq = self.store.max_seq()
        for rec in self.store.unfinished():
            if rec.cancel_requested:  # stored, but the last scheduler died before acting on it
                log.info("job %s: canceled (the cancel was stored before a restart)", rec.id)
                self.states.end(rec.id, "canceled", finished_at=time.time())
                continue
            ck = checkpoint.load_checkpoint(self.job_dir(rec.id))
            log.info("re-queueing job %s (was %s, resumes at pass %d of %d)", rec.id, rec.state,
                     ck.next_pass if ck else 0, rec.passes_total)
            if rec.state == "queued" or self.states.move(
                    rec.id, "queued", UNFINISHED,
                    passes_done=ck.next_pass + len(ck.done) if ck else 0):
                self._enqueue(rec.id)
        for i in range(self.settings.max_concurrent_jobs):
            self._spawn(self._worker, f"nprt-worker-{i}")
        self._spawn(self._poll, "nprt-scheduler-poll")
        log.info("scheduler up: data dir %s, %d job slot(s)", self.settings.data_dir,
                 self.settings.max_concurrent_jobs)
        return self

    def _spawn(self, target, name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def _take_lock(self, wait_s: float = LOCK_WAIT_S) -> None:
        path = self.settings.data_dir / LOCK_NAME
        f = path.open("a+")
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline or self._stopping.is_set():
                    f.close()
                    raise SchedulerRunning(f"another scheduler runs on {self.settings.data_dir}"
                                           f" (it held {LOCK_NAME} for {wait_s:.0f} s)") from None
                time.sleep(0.2)
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        self._lock_file = f

    def stop(self, timeout_s: float | None = 30.0) -> None:
        """Interrupt renders at their next pass boundary; their jobs stay unfinished in the
        store, so the next start resumes them from the checkpoint. Then close the warm
        pools, stop a Ray this scheduler started (its processes and agents included) and
        join every thread it started. timeout_s None waits for the renders however long
        they take; a render still running after a finite timeout_s keeps Ray and its
        thread (they go when the process exits)."""
        self._stopping.set()
        with self._lock:
            for live in self._live.values():
                live.cancel.set()
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._idle:
            self._idle.wait_for(lambda: not self._running, timeout_s)
            idle = not self._running
        if idle:
            self.pools.close()
        for _ in range(self.settings.max_concurrent_jobs):
            self._queue.put(None)
        for t in self._threads:
            t.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        running = [t.name for t in self._threads if t.is_alive()]
        if running or not idle:  # never pull Ray from under a render; it goes at exit
            log.warning("%s still rendering after %.0f s; leaving Ray up", running, timeout_s)
        else:
            self.ray.shutdown()
        self.store.close()
        if self._lock_file is not None:
            self._lock_file.close()  # releases the lock

    def job_dir(self, job_id: str) -> Path:
        return self.settings.jobs_dir / job_id

    # ------------------------------------------------------------ the store poller

    def _poll(self) -> None:
        pruned_at = 0.0
        while not self._stopping.wait(POLL_S):
            try:
                self.poll_once()
                if time.monotonic() - pruned_at > PRUNE_EVERY_S:
                    now = time.time()
                    self.store.prune_events(now - TILE_EVENT_KEEP_S, now - STATE_EVENT_KEEP_S)
                    pruned_at = time.monotonic()
            except Exception:  # a busy store: the next poll catches up
                log.exception("reading the job store failed")

    def poll_once(self) -> None:
        """Queue the jobs stored since the last look; act on cancels of held jobs."""
        for seq, job_id in self.store.queued_after(self._seen_seq):
            self._seen_seq = seq
            self._enqueue(job_id)
        with self._lock:
            held = list(self._running)
        for job_id in self.store.cancels_among(held):
            with self._lock:
                live = self._live.get(job_id)
            if live is not None and not live.cancel.is_set():
                log.info("job %s: cancel requested", job_id)
                live.cancel.set()

    # ------------------------------------------------------------ job slots

    def _enqueue(self, job_id: str) -> None:
        with self._lock:
            if job_id in self._live:
                return
            self._live[job_id] = LiveJob()
        self._queue.put(job_id)

    def _worker(self) -> None:
        while (job_id := self._queue.get()) is not None:
            if self._stopping.is_set():
                return
            requeue = False
            with self._lock:
                self._running.add(job_id)
            try:
                requeue = self._run(job_id)
            except Exception:  # keep the worker alive for the next job
                log.exception("job %s: unexpected error in the scheduler", job_id)
            finally:
                with self._lock:
                    self._live.pop(job_id, None)
                    self._running.discard(job_id)
                    self._idle.notify_all()
            if requeue:
                self._enqueue(job_id)

    def _run(self, job_id: str) -> bool:
        """Render one job; True when it went back to the queue (its shards were lost)."""
        rec = self.store.get(job_id)
        if rec is None or rec.state in TERMINAL:
            return False
        job_dir = self.job_dir(job_id)
        job_dir.mkdir(parents=True, exist_ok=True)
        settings = RenderSettings.model_validate(rec.settings)
        with self._lock:
            live = self._live[job_id]
        with job_log(job_dir / "job.log"):
            if settings.shards == 0:
                return self.runner.run(rec, job_dir, settings, live)
            log.info("job %s: waiting for a sharded-job slot", job_id)
            # The job stays queued (and cancellable) meanwhile.
            while not self._sharded_slots.acquire(timeout=SLOT_POLL_S):
                if live.cancel.is_set() or self._stopping.is_set():
                    return False
            try:
                rec = self.store.get(job_id)
                if rec.state in TERMINAL or self._stopping.is_set():
                    return False
                return self.runner.run(rec, job_dir, settings, live)
            finally:
                self._sharded_slots.release()
