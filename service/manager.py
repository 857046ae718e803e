"""The job manager: stores every job before it runs, renders FIFO on a bounded pool of
threads on warm shard pools, checkpoints every few seconds, and re-queues unfinished jobs
on startup.

State changes are compare-and-set in the store: a cancel is stored before it is acted on
and wins over a late success, and nothing leaves a terminal state."""

from __future__ import annotations

import json
import logging
import queue
import shutil
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nprt.scene.errors import SceneError
from nprt.service import checkpoint, images
from nprt.service.config import ServiceSettings
from nprt.service.errors import Conflict, InvalidJob, NotFound, redact_paths
from nprt.service.events import EventBroker, Notify, Subscription
from nprt.service.joblog import job_log
from nprt.service.scenes import SceneStore
from nprt.service.store import TERMINAL, UNFINISHED, JobRecord, JobStore
from nprt.workers.film import Film
from nprt.workers.passes import count_passes
from nprt.workers.render import PassDone, Progress, RenderCanceled, make_renderer, render
from nprt.workers.runtime.pool import PoolRegistry
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
SLOT_POLL_S = 0.5  # how often a job waiting for a sharded-job slot looks for its cancel
RAY_RETRY_S = 2.0  # back-off between tries at starting Ray, times the attempt number


class RayUnavailable(RuntimeError):
    """Starting or joining Ray failed every attempt; the message names the address."""


@dataclass
class _Live:
    """What exists only while this process owns a queued or running job."""

    cancel: threading.Event = field(default_factory=threading.Event)
    film: Film | None = None  # the render's film; read it under film.lock
    progress: Progress | None = None
    stats: RenderStats | None = None
    saved_at: float = 0.0  # monotonic time of the last checkpoint
    stored_at: float = 0.0  # ... and of the last progress write to the store
    checkpoint_bytes: int = 0


class JobManager:
    def __init__(self, settings: ServiceSettings, scenes: SceneStore,
                 store: JobStore | None = None, broker: EventBroker | None = None):
        self.settings = settings
        self.scenes = scenes
        self.store = store or JobStore(settings.db_path)
        self.broker = broker or EventBroker(settings.max_watchers, settings.watcher_tile_bytes)
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._live: dict[str, _Live] = {}
        self._lock = threading.Lock()
        self._active = 0  # jobs being run by worker threads
        self._idle = threading.Condition(self._lock)
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self._ray_lock = threading.Lock()
        self._started_ray = False
        # Without placement groups, two Coordinators that each ask for the whole cluster can
        # each get part of their actors and then wait on each other for ever.
        self._sharded_slots = threading.BoundedSemaphore(settings.max_sharded_jobs)
        self.pools = PoolRegistry(settings.pool_max_bytes, settings.pool_max_count)
        settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        self._server_roots = [str(REPO), str(settings.data_dir.absolute()),
                              str(settings.data_dir.resolve())]

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        for rec in self.store.unfinished():
            if rec.cancel_requested:  # stored, but the last process died before acting on it
                log.info("job %s: canceled (the cancel was stored before a restart)", rec.id)
                self._end(rec.id, "canceled", finished_at=time.time())
                continue
            ck = checkpoint.load_checkpoint(self.job_dir(rec.id))
            log.info("re-queueing job %s (was %s, resumes at pass %d of %d)", rec.id, rec.state,
                     ck.next_pass if ck else 0, rec.passes_total)
            if self.store.transition(rec.id, "queued", UNFINISHED,
                                     passes_done=ck.next_pass + len(ck.done) if ck else 0):
                self._enqueue(rec.id)
        for i in range(self.settings.max_concurrent_jobs):
            t = threading.Thread(target=self._worker, name=f"nprt-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout_s: float = 30.0) -> None:
        """Interrupt renders at their next pass boundary; their jobs stay unfinished in the
        store, so the next start resumes them from the checkpoint."""
        self._stopping.set()
        with self._lock:
            for live in self._live.values():
                live.cancel.set()
        deadline = time.monotonic() + timeout_s
        with self._idle:
            self._idle.wait_for(lambda: self._active == 0, timeout_s)
            idle = self._active == 0
        if idle:
            # Before the workers exit: Ray's processes die with the thread that started
            # them (parent-death signal), and closing a pool needs them.
            self.pools.close()
        for _ in self._threads:
            self._queue.put(None)
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        running = [t.name for t in self._threads if t.is_alive()]
        if running or not idle:  # never pull Ray from under a render; it goes at exit
            log.warning("%s still rendering after %.0f s; leaving Ray up", running, timeout_s)
        elif self._started_ray:
            import ray

            ray.shutdown()
        self.store.close()

    # ------------------------------------------------------------ API

    def submit(self, scene: str, settings: RenderSettings,
               idempotency_key: str | None = None,
               frames: tuple[int, int] | None = None) -> tuple[JobRecord, bool]:
        """Store a queued job in O(1) time and memory; returns (job, created). frames:
        (first, last) frames of an animated scene, inclusive, one image each (checked
        against the scene when the job loads it). A stored idempotency key returns its
        job again (created False), Conflict if the request differs."""
        frames = None if frames is None else [int(frames[0]), int(frames[1])]
        n_frames = 1 if frames is None else frames[1] - frames[0] + 1
        if n_frames < 1:
            raise InvalidJob("frames", f"last frame {frames[1]} is before first {frames[0]}")
        self._check_cost(settings, n_frames)
        self.scenes.check(scene)
        stored = settings.model_dump(mode="json")
        job_id = uuid.uuid4().hex
        rec = self.store.insert(job_id, scene, stored, count_passes(settings) * n_frames,
                                idempotency_key, frames)
        if rec.id != job_id:  # the key was stored already
            if (rec.scene, rec.settings, rec.frames) != (scene, stored, frames):
                raise Conflict(f"Idempotency-Key {idempotency_key!r} was used for job {rec.id} "
                               "with a different request")
            return rec, False
        self._enqueue(rec.id)  # the worker makes the job directory
        log.info("job %s queued: scene %r, %dx%d, %d spp, mode %s, shards %d", rec.id, scene,
                 settings.width, settings.height, settings.spp, settings.mode, settings.shards)
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

    def get(self, job_id: str) -> JobRecord:
        rec = self.store.get(job_id)
        if rec is None:
            raise NotFound(f"no job with id {job_id!r}")
        return rec

    def list(self, offset: int = 0, limit: int = 50, state: str | None = None):
        return self.store.list(offset, limit, state)

    def cancel(self, job_id: str) -> JobRecord:
        """Store the cancel, then act on it: a queued job is canceled at once, a running one
        stops at its next pass boundary. Conflict if the job already finished."""
        if not self.store.request_cancel(job_id):
            rec = self.get(job_id)
            raise Conflict(f"job {job_id} already {rec.state}; nothing to cancel")
        with self._lock:
            live = self._live.get(job_id)
        if live is not None:
            live.cancel.set()
        rec = self.get(job_id)
        if rec.state == "canceled":
            self.broker.publish(job_id, {"type": "state", "job": rec})
        log.info("job %s: cancel requested (now %s)", job_id, rec.state)
        return rec

    def watch(self, job_id: str, notify: Notify) -> Subscription:
        """Collect `job_id`'s events for one watcher (TooManyWatchers over the limit)."""
        return self.broker.subscribe(job_id, notify)

    def delete(self, job_id: str) -> None:
        """Forget a terminal job: its row and its folder (image, checkpoint, job.log)."""
        rec = self.get(job_id)
        if rec.state not in TERMINAL:
            raise Conflict(f"job {job_id} is {rec.state}; cancel it before deleting it")
        self.store.delete(job_id)
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)
        log.info("job %s deleted", job_id)

    def image(self, job_id: str, fmt: str) -> tuple[bytes, bool]:
        """(encoded image, partial): the final file once succeeded, else the latest pass."""
        rec = self.get(job_id)
        s = rec.settings
        final = self.job_dir(job_id) / f"image.{fmt}"
        if rec.state == "succeeded" and final.exists():
            return final.read_bytes(), False
        with self._lock:
            live = self._live.get(job_id)
            film = live.film if live else None
        sums = samples = None
        if film is not None:
            with film.lock:
                sums, samples = film.sums.copy(), film.samples.copy()
        if sums is None:
            ck = checkpoint.load_checkpoint(self.job_dir(job_id))
            if ck is None:
                raise NotFound(f"job {job_id} has no image yet (state {rec.state}, "
                               f"{rec.passes_done} of {rec.passes_total} passes done)")
            sums, samples = ck.sums, ck.samples
        img = images.film_image(sums, samples, s["width"], s["height"])
        return images.encode(img, fmt), True

    def frame_image(self, job_id: str, frame: int, fmt: str) -> bytes:
        """The encoded image of one finished frame of a frames job (NotFound otherwise)."""
        rec = self.get(job_id)
        if rec.frames is None or not rec.frames[0] <= frame <= rec.frames[1]:
            have = "renders no frames" if rec.frames is None else \
                f"renders frames {rec.frames[0]} to {rec.frames[1]}"
            raise NotFound(f"job {job_id} {have}; no frame {frame}")
        path = _frame_file(self.job_dir(job_id), frame, fmt)
        if not path.exists():
            raise NotFound(f"job {job_id}: frame {frame} is not rendered yet (state "
                           f"{rec.state})")
        return path.read_bytes()

    def job_dir(self, job_id: str) -> Path:
        return self.settings.jobs_dir / job_id

    # ------------------------------------------------------------ workers

    def _enqueue(self, job_id: str) -> None:
        with self._lock:
            self._live[job_id] = _Live()
        self._queue.put(job_id)

    def _worker(self) -> None:
        while (job_id := self._queue.get()) is not None:
            if self._stopping.is_set():
                return
            requeue = False
            with self._lock:
                self._active += 1
            try:
                requeue = self._run(job_id)
            except Exception:  # keep the worker alive for the next job
                log.exception("job %s: unexpected error in the job manager", job_id)
            finally:
                with self._lock:
                    self._live.pop(job_id, None)
                    self._active -= 1
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
                return self._render(rec, job_dir, settings, live)
            log.info("job %s: waiting for a sharded-job slot", job_id)
            # The job stays queued (and cancellable) meanwhile.
            while not self._sharded_slots.acquire(timeout=SLOT_POLL_S):
                if live.cancel.is_set() or self._stopping.is_set():
                    return False
            try:
                rec = self.store.get(job_id)
                if rec.state in TERMINAL or self._stopping.is_set():
                    return False
                return self._render(rec, job_dir, settings, live)
            finally:
                self._sharded_slots.release()

    def _render(self, rec: JobRecord, job_dir: Path, settings: RenderSettings,
                live: _Live) -> bool:
        job_id = rec.id
        if not self._move(job_id, "preparing", ("queued",),
                          started_at=rec.started_at or time.time()):
            return False  # canceled while queued
        resume = checkpoint.load_checkpoint(job_dir)
        log.info("job %s: preparing scene %r%s", job_id, rec.scene,
                 f" (resuming at pass {resume.next_pass})" if resume else "")
        renderer = None
        try:
            scene = self.scenes.load(rec.scene)
            _check_cancel(live, "loading the scene")
            if settings.shards > 0:
                self._ensure_ray()
                _check_cancel(live, "starting Ray")
            renderer = make_renderer(
                scene, settings, ray_address=self.settings.ray_address,
                proxy_dir=self.settings.proxies_dir, pools=self.pools,
                on_progress=lambda rows: self.store.update(
                    job_id, stats={"proxy_training": rows}))
            _check_cancel(live, "starting the renderer")
            self._move(job_id, "running", ("preparing",))
            if rec.frames is not None:
                result = self._render_frames(rec, job_dir, settings, live, scene, renderer)
            else:
                result = render(scene, settings, resume=resume, cancel=live.cancel,
                                renderer=renderer,
                                on_pass=lambda p: self._on_pass(job_id, job_dir, live, p))
            renderer.close()
            renderer = None
            self._finish(job_id, job_dir, result)
        except RenderCanceled as e:
            if self._stopping.is_set() and not self.store.get(job_id).cancel_requested:
                self._checkpoint(job_dir, live)
                log.info("job %s: interrupted by shutdown; resumes on next start", job_id)
                return False
            log.info("job %s: %s", job_id, e)
            self._end(job_id, "canceled", finished_at=time.time())
        except SceneError as e:
            log.error("job %s: scene %r failed to load: %s", job_id, rec.scene, e)
            self._end(job_id, "failed", error=self._redact(str(e)), finished_at=time.time())
        except Exception as e:
            if _shards_lost(e) and self._requeue(job_id, e):
                return True
            log.exception("job %s failed", job_id)
            self._end(job_id, "failed", error=self._redact(f"{type(e).__name__}: {e}"),
                      finished_at=time.time())
        finally:
            if renderer is not None:
                renderer.close()
        return False

    def _render_frames(self, rec: JobRecord, job_dir: Path, settings: RenderSettings,
                       live: _Live, scene, renderer):
        """Each frame of rec.frames in turn on one renderer (the shards keep geometry and
        proxies; only the instance table and lights change), each stored as
        frames/NNNNN.png and .exr. A job resumed after a restart skips the frames stored
        and re-renders the one it was in. Returns the last frame's RenderResult."""
        from nprt.scene.animation import frame_range

        frames = frame_range(f"{rec.frames[0]}:{rec.frames[1]}", scene.frames)
        per = count_passes(settings)
        checkpoint.clear_checkpoint(job_dir)  # a frame's partial film is not resumed
        todo = [f for f in frames if not _frame_file(job_dir, f, "exr").exists()]
        # Every frame was stored before a restart: the last one again, for the final image.
        result, walls = None, {}
        for f in todo or [frames[-1]]:
            i = f - frames[0]
            t0 = time.perf_counter()
            at = scene.at_frame(f)
            renderer.set_frame(at)
            result = render(at, settings, cancel=live.cancel, renderer=renderer,
                            on_pass=lambda p, base=i * per: self._on_pass(
                                rec.id, job_dir, live, p, base, rec.passes_total))
            img = result.film.image()
            (job_dir / "frames").mkdir(exist_ok=True)
            checkpoint.atomic_write_bytes(_frame_file(job_dir, f, "png"), images.png_bytes(img))
            checkpoint.atomic_write_bytes(_frame_file(job_dir, f, "exr"), images.exr_bytes(img))
            walls[str(f)] = round(time.perf_counter() - t0, 4)
            log.info("job %s: frame %d done in %.2f s", rec.id, f, walls[str(f)])
        result.info["passes"] = per * len(frames)
        result.info["frames"] = {"first": frames[0], "last": frames[-1], "frame_wall_s": walls}
        return result

    def _requeue(self, job_id: str, exc: Exception) -> bool:
        """Send a job whose Ray node was lost back to the queue; it resumes from its
        checkpoint on fresh shards, at most max_job_retries times."""
        limit = self.settings.max_job_retries
        if not self.store.requeue(job_id, limit):
            return False
        rec = self.store.get(job_id)
        log.warning("job %s: lost its shards (%s); re-queued from pass %d, retry %d of %d",
                    job_id, exc, rec.passes_done, rec.retries, limit)
        self.broker.publish(job_id, {"type": "state", "job": rec})
        return True

    def _ensure_ray(self) -> None:
        """Start or join Ray once for the whole service, retrying a failed start. A
        Coordinator that started Ray itself would shut it down when its job ends, under any
        other sharded job, and every job would pay the start-up again."""
        import ray

        from nprt.workers.runtime.raysession import ensure_ray

        address, attempts = self.settings.ray_address, self.settings.ray_start_attempts
        with self._ray_lock:
            for attempt in range(1, attempts + 1):
                try:
                    if ensure_ray(address):
                        self._started_ray = True
                        where = f"joined Ray at {address}" if address else "started a local Ray"
                        log.info("%s for this service", where)
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

    def _checkpoint(self, job_dir: Path, live: _Live) -> None:
        """Save the film and the set of passes it holds (O(film); every few seconds)."""
        if live.film is None:
            return
        with live.film.lock:
            sums, samples = live.film.sums.copy(), live.film.samples.copy()
            done = sorted(live.progress.done)
            next_pass, stats = live.progress.next_pass, live.stats.to_dict()
        live.checkpoint_bytes += checkpoint.save_checkpoint(job_dir, next_pass, sums, samples,
                                                            stats, done)
        live.saved_at = time.monotonic()

    def _on_pass(self, job_id: str, job_dir: Path, live: _Live, p: PassDone, base: int = 0,
                 total: int | None = None) -> None:
        """After each pass: a tile event (the tile's pixels only); every
        checkpoint_interval_s a checkpoint and a progress write to the store. base, total:
        passes of the frames before this one, and of the whole job (frames jobs)."""
        total = total or p.total
        live.film, live.progress, live.stats = p.film, p.progress, p.stats
        now = time.monotonic()
        if now - live.saved_at >= self.settings.checkpoint_interval_s:
            self._checkpoint(job_dir, live)
        if now - live.stored_at >= min(1.0, self.settings.checkpoint_interval_s):
            self.store.update(job_id, passes_done=base + p.progress.count,
                              stats=p.stats.to_dict())
            live.stored_at = now
        if not self.broker.subscribers(job_id):
            return
        t = p.pass_
        pix = t.pixels(p.film.width)
        with p.film.lock:
            rgb = (p.film.sums[pix] / np.maximum(p.film.samples[pix], 1)[:, None])
        rgb = rgb.astype(np.float32)
        self.broker.publish(job_id, {
            "type": "tile", "pass_index": p.index, "passes_total": p.total,
            "rect": (t.x0, t.y0, t.x1, t.y1), "sample0": t.sample0, "sample1": t.sample1,
            "progress": (base + p.progress.count) / total,
            "rgb": rgb.reshape(t.y1 - t.y0, t.x1 - t.x0, 3),
        })

    def _finish(self, job_id: str, job_dir: Path, result) -> None:
        film = result.film
        img = film.image()
        (job_dir / "image.png").write_bytes(images.png_bytes(img))
        (job_dir / "image.exr").write_bytes(images.exr_bytes(img))
        stats = result.stats_dict()
        with self._lock:
            live = self._live.get(job_id)
        if live is not None:
            stats["checkpoint_bytes"] = live.checkpoint_bytes
        checkpoint.atomic_write_bytes(job_dir / "stats.json",
                                      json.dumps(stats, indent=1, default=str).encode())
        # The final film stays on disk: it proves every pixel got its samples.
        checkpoint.atomic_save_npy(job_dir / "sums.npy", film.sums)
        checkpoint.atomic_save_npy(job_dir / "samples.npy", film.samples)
        pixel_samples = {"min": int(film.samples.min()), "max": int(film.samples.max())}
        state = self._end(job_id, "succeeded", finished_at=time.time(),
                          stats=json.loads(json.dumps(stats, default=str)),
                          pixel_samples=pixel_samples, passes_done=result.info["passes"])
        checkpoint.clear_checkpoint(job_dir)
        log.info("job %s %s in %.2f s", job_id, state or "finished already",
                 result.info.get("wall_s", 0.0))

    def _move(self, job_id: str, state: str, from_states: tuple[str, ...], **fields) -> bool:
        """Compare-and-set to a non-terminal state; watchers hear of it when it happened."""
        moved = self.store.transition(job_id, state, from_states, **fields)
        if moved:
            self.broker.publish(job_id, {"type": "state", "job": self.store.get(job_id)})
        return moved

    def _end(self, job_id: str, state: str, **fields) -> str | None:
        """Enter a terminal state unless the job has one already; returns the state it got
        (a stored cancel turns success into canceled)."""
        got = self.store.finish(job_id, state, **fields)
        if got is not None:
            self.broker.publish(job_id, {"type": "state", "job": self.store.get(job_id)})
        return got

    def _redact(self, message: str) -> str:
        return redact_paths(message, self._server_roots)


def _frame_file(job_dir: Path, frame: int, fmt: str) -> Path:
    return job_dir / "frames" / f"{frame:05d}.{fmt}"


def _check_cancel(live: _Live, stage: str) -> None:
    if live.cancel.is_set():
        raise RenderCanceled(f"canceled while {stage}")


def _shards_lost(exc: BaseException) -> bool:
    """Whether a render failed because Ray lost its shards (a node died), not by a bug."""
    # never imported: no shards to lose
    coordinator = sys.modules.get("nprt.workers.runtime.coordinator")
    return coordinator is not None and isinstance(exc, coordinator.ShardsLost)
