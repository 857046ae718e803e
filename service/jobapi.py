"""What an API worker does with jobs: validate and store (O(1), bounded by the queue
depth), read, cancel, delete, read images from the job's folder, and watch through the
event feed. It never renders: the scheduler process (nprt.service.scheduler) picks stored
jobs up, so any number of API workers can share one store."""

from __future__ import annotations

import logging
import os
import shutil
import sqlite3
import threading
from pathlib import Path

from pydantic_core import from_json

from nprt.service import checkpoint, images
from nprt.service.config import ServiceSettings
from nprt.service.errors import Conflict, InvalidJob, NotFound, QueueFull, StoreBusy
from nprt.service.events import EventBroker, Notify, Subscription
from nprt.service.feed import EventFeed
from nprt.service.scenes import SceneStore
from nprt.service.store import TERMINAL, JobRecord, JobStore
from nprt.service.store import QueueFull as StoreQueueFull
from nprt.service.storewriter import StoreWriter
from nprt.workers.passes import count_passes
from nprt.workers.settings import RenderSettings

log = logging.getLogger(__name__)


class JobApi:
    def __init__(self, settings: ServiceSettings, scenes: SceneStore,
                 store: JobStore | None = None):
        self.settings = settings
        self.scenes = scenes
        self.store = store or JobStore(settings.db_path)
        self.broker = EventBroker(settings.max_watchers, settings.watcher_tile_bytes)
        # Its own connection: the feed's reads never wait on this worker's requests.
        self._feed = EventFeed(JobStore(settings.db_path), self.broker)
        # One thread for the store's writes: they serialise on its connection anyway, and
        # admissions that queue up meanwhile share one commit.
        self._writer = StoreWriter(self.store)
        settings.jobs_dir.mkdir(parents=True, exist_ok=True)

    def start(self) -> JobApi:
        self._feed.start()
        return self

    def stop(self) -> None:
        self._writer.stop()
        self._feed.stop()
        self._feed.store.close()
        self.store.close()

    # ------------------------------------------------------------ writes (off the loop)

    async def in_writer(self, fn, *args):
        """fn(*args) on the writer thread: a write may wait for another process's, and
        must not hold the event loop meanwhile."""
        return await self._writer.call(fn, *args)

    def submit(self, scene: str, settings: RenderSettings,
               idempotency_key: str | None = None,
               frames: tuple[int, int] | None = None) -> tuple[JobRecord, bool]:
        """Store a queued job in O(1) time and memory; returns (job, created). frames:
        (first, last) frames of an animated scene, inclusive, one image each (checked
        against the scene when the job loads it). A stored idempotency key returns its
        job again (created False), Conflict if the request differs; QueueFull past
        max_queued_jobs."""
        row = self._row(scene, settings, idempotency_key, frames)
        try:
            return self._created(row, self.store.insert(*row))
        except (StoreQueueFull, sqlite3.OperationalError) as e:
            raise _refusal(e) from None

    async def submit_async(self, scene: str, settings: RenderSettings,
                           idempotency_key: str | None = None,
                           frames: tuple[int, int] | None = None) -> tuple[JobRecord, bool]:
        """submit() from the event loop: checked here, stored on the writer thread in one
        transaction with the admissions queued beside it. settings may be the validated
        JobCreate itself: only its RenderSettings fields are stored."""
        row = self._row(scene, settings, idempotency_key, frames)
        try:
            return self._created(row, await self._writer.insert(*row))
        except (StoreQueueFull, sqlite3.OperationalError) as e:
            raise _refusal(e) from None

    def _row(self, scene: str, settings: RenderSettings, idempotency_key: str | None,
             frames: tuple[int, int] | None) -> tuple:
        """The store row of a valid job (InvalidJob, UnknownScene otherwise); its settings
        as JSON text."""
        frames = None if frames is None else [int(frames[0]), int(frames[1])]
        n_frames = 1 if frames is None else frames[1] - frames[0] + 1
        if n_frames < 1:
            raise InvalidJob("frames", f"last frame {frames[1]} is before first {frames[0]}")
        self._check_cost(settings, n_frames)
        self.scenes.check(scene)
        return (new_job_id(), scene, settings_json(settings),
                count_passes(settings) * n_frames, idempotency_key, frames,
                self.settings.max_queued_jobs)

    @staticmethod
    def _created(row: tuple, rec: JobRecord) -> tuple[JobRecord, bool]:
        job_id, scene, stored, _, key, frames, _ = row
        if rec.id != job_id:  # the key was stored already
            if (rec.scene, rec.settings, rec.frames) != (scene, from_json(stored), frames):
                raise Conflict(f"Idempotency-Key {key!r} was used for job {rec.id} "
                               "with a different request")
            return rec, False
        return rec, True

    def _check_cost(self, s: RenderSettings, n_frames: int = 1) -> None:
        """InvalidJob naming the field when a job is over a configured limit (its samples
        count every frame)."""
        pixels, limit = s.width * s.height, self.settings.max_image_pixels
        if pixels > limit:
            raise InvalidJob("width", f"{s.width}x{s.height} = {pixels} pixels is over the "
                             f"service limit of {limit} (NPRT_MAX_IMAGE_PIXELS)")
        samples, limit = pixels * s.spp * n_frames, self.settings.max_job_samples
        if samples > limit:
            per = f" x {n_frames} frames" if n_frames > 1 else ""
            raise InvalidJob("frames" if n_frames > 1 else "spp",
                             f"{s.width}x{s.height} x {s.spp} spp{per} = {samples} samples "
                             f"is over the service limit of {limit} (NPRT_MAX_JOB_SAMPLES)")

    def cancel(self, job_id: str) -> JobRecord:
        """Store the cancel: a queued job is canceled at once, a running one stops at its
        next pass boundary (the scheduler reads the stored cancel). Conflict if the job
        already finished."""
        if not self.store.request_cancel(job_id):
            rec = self.get(job_id)
            raise Conflict(f"job {job_id} already {rec.state}; nothing to cancel")
        rec = self.get(job_id)
        if rec.state == "canceled":  # the scheduler will not hear of it: tell the watchers
            self.store.state_event(job_id)
        log.info("job %s: cancel requested (now %s)", job_id, rec.state)
        return rec

    def delete(self, job_id: str) -> None:
        """Forget a terminal job: its row and its folder (image, checkpoint, job.log)."""
        rec = self.get(job_id)
        if rec.state not in TERMINAL:
            raise Conflict(f"job {job_id} is {rec.state}; cancel it before deleting it")
        self.store.delete(job_id)
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)
        log.info("job %s deleted", job_id)

    # ------------------------------------------------------------ reads

    def get(self, job_id: str) -> JobRecord:
        rec = self.store.get(job_id)
        if rec is None:
            raise NotFound(f"no job with id {job_id!r}")
        return rec

    def list(self, offset: int = 0, limit: int = 50, state: str | None = None):
        return self.store.list(offset, limit, state)

    def watch(self, job_id: str, notify: Notify) -> Subscription:
        """Collect `job_id`'s events for one watcher (TooManyWatchers over the limit)."""
        return self.broker.subscribe(job_id, notify)

    def image(self, job_id: str, fmt: str) -> tuple[bytes, bool]:
        """(encoded image, partial): the final file once succeeded, else the latest
        checkpoint (the scheduler writes one after the first pass, then every
        checkpoint_interval_s)."""
        rec = self.get(job_id)
        s = rec.settings
        final = self.job_dir(job_id) / f"image.{fmt}"
        if rec.state == "succeeded" and final.exists():
            return final.read_bytes(), False
        ck = checkpoint.read_checkpoint(self.job_dir(job_id))
        if ck is None:
            raise NotFound(f"job {job_id} has no image yet (state {rec.state}, "
                           f"{rec.passes_done} of {rec.passes_total} passes done)")
        img = images.film_image(ck.sums, ck.samples, s["width"], s["height"])
        return images.encode(img, fmt), True

    def frame_image(self, job_id: str, frame: int, fmt: str) -> bytes:
        """The encoded image of one finished frame of a frames job (NotFound otherwise)."""
        rec = self.get(job_id)
        if rec.frames is None or not rec.frames[0] <= frame <= rec.frames[1]:
            have = "renders no frames" if rec.frames is None else \
                f"renders frames {rec.frames[0]} to {rec.frames[1]}"
            raise NotFound(f"job {job_id} {have}; no frame {frame}")
        path = checkpoint.frame_file(self.job_dir(job_id), frame, fmt)
        if not path.exists():
            raise NotFound(f"job {job_id}: frame {frame} is not rendered yet (state "
                           f"{rec.state})")
        return path.read_bytes()

    def job_dir(self, job_id: str) -> Path:
        return self.settings.jobs_dir / job_id


def settings_json(settings: RenderSettings) -> str:
    """The JSON text of the RenderSettings fields of `settings` (a RenderSettings or a
    subclass such as the validated JobCreate, whose other fields are left out), as the store
    keeps it; pydantic serialises it in a fraction of json.dumps(model_dump())'s time."""
    return _SETTINGS_SERIALIZER.to_json(settings).decode()


_SETTINGS_SERIALIZER = RenderSettings.__pydantic_serializer__


class _JobIds:
    """uuid4 hex ids from os.urandom, a batch of random bytes at a time: os.urandom releases
    the GIL, and on an event loop sharing it with the store writer and event feed threads
    each release waited for a thread to hand it back (a tenth of an admission's time under
    py-spy in a burst)."""

    BATCH = 256

    def __init__(self):
        self._lock = threading.Lock()  # the gRPC servicer admits from its threads
        self._ids: list[str] = []
        # A forked child drawing the parent's batch would repeat its ids.
        os.register_at_fork(after_in_child=self._forget)

    def __call__(self) -> str:
        with self._lock:
            if not self._ids:
                self._ids = _uuid4_hexes(self.BATCH)
            return self._ids.pop()

    def _forget(self) -> None:
        self._ids = []


def _uuid4_hexes(n: int) -> list[str]:
    """n random uuid4s as 32 hex digits (uuid.uuid4().hex), from one os.urandom call: the
    version and variant bits set on the bytes, a fraction of building each UUID."""
    raw = bytearray(os.urandom(16 * n))
    raw[6::16] = bytes(b & 0x0F | 0x40 for b in raw[6::16])  # version 4
    raw[8::16] = bytes(b & 0x3F | 0x80 for b in raw[8::16])  # variant RFC 4122
    text = raw.hex()
    return [text[i:i + 32] for i in range(0, len(text), 32)]


new_job_id = _JobIds()


def _refusal(e: Exception) -> Exception:
    if isinstance(e, StoreQueueFull):
        return QueueFull(str(e))
    # another process held the write lock too long
    return StoreBusy(f"the job store is busy ({e}); try again")
