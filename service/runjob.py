"""Rendering one job in the scheduler process: load the scene, make the renderer (the
reference, or a Coordinator on a warm shard pool), render one image or a frame range
(nprt.workers.frames), and after each pass write progress, tiles and, every few seconds, a
checkpoint; then store the outputs and the final state."""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from nprt.scene.errors import SceneError
from nprt.service import checkpoint, images
from nprt.service.errors import redact_paths
from nprt.service.jobstates import JobStates
from nprt.service.store import JobRecord
from nprt.service.tiles import publish_tile
from nprt.workers.film import Film
from nprt.workers.frames import render_frames
from nprt.workers.passes import count_passes
from nprt.workers.render import PassDone, Progress, RenderCanceled, make_renderer, render
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]


@dataclass
class LiveJob:
    """What exists only while the scheduler holds a queued or running job."""

    cancel: threading.Event = field(default_factory=threading.Event)
    film: Film | None = None  # the render's film; read it under film.lock
    progress: Progress | None = None
    stats: RenderStats | None = None
    saved_at: float = 0.0  # monotonic time of the last checkpoint
    stored_at: float = 0.0  # ... and of the last progress write to the store
    checkpoint_bytes: int = 0


class JobRunner:
    """Renders jobs for the Scheduler, which gives it Ray, the pools and the settings."""

    def __init__(self, scheduler):
        self.sched = scheduler
        self.settings = scheduler.settings
        self.store = scheduler.store
        self.states = JobStates(scheduler.store)
        self._roots = [str(REPO), str(self.settings.data_dir.absolute()),
                       str(self.settings.data_dir.resolve())]

    def run(self, rec: JobRecord, job_dir: Path, settings: RenderSettings,
            live: LiveJob) -> bool:
        """Render one job; True when it went back to the queue (its shards were lost)."""
        job_id = rec.id
        if not self.states.move(job_id, "preparing", ("queued",),
                                started_at=rec.started_at or time.time()):
            return False  # canceled while queued
        resume = checkpoint.load_checkpoint(job_dir)
        log.info("job %s: preparing scene %r%s", job_id, rec.scene,
                 f" (resuming at pass {resume.next_pass})" if resume else "")
        try:
            scene = self.sched.scenes.load(rec.scene)
            self._check_cancel(job_id, live, "loading the scene")
            if settings.shards > 0:
                self.sched.ray.ensure()
                self._check_cancel(job_id, live, "starting Ray")
            renderer = make_renderer(
                scene, settings, ray_address=self.settings.ray_address,
                proxy_dir=self.settings.proxies_dir, pools=self.sched.pools,
                on_progress=lambda rows: self.store.update(
                    job_id, stats={"proxy_training": rows}))
            # Closed before the job's end is published, whatever the end: a job shown
            # canceled or failed holds no shards (its pool is back in the registry).
            try:
                self._check_cancel(job_id, live, "starting the renderer")
                self.states.move(job_id, "running", ("preparing",))
                if rec.frames is not None:
                    result = self._frames(rec, job_dir, settings, live, scene, renderer)
                else:
                    result = render(scene, settings, resume=resume, cancel=live.cancel,
                                    renderer=renderer,
                                    on_pass=lambda p: self.on_pass(job_id, job_dir, live, p))
            finally:
                renderer.close()
            self._check_accuracy(scene, settings, result)
            self._finish(job_id, job_dir, result, live)
        except RenderCanceled as e:
            if self.sched.stopping and not self.store.get(job_id).cancel_requested:
                self.checkpoint(job_dir, live)
                log.info("job %s: interrupted by shutdown; resumes on next start", job_id)
                return False
            log.info("job %s: %s", job_id, e)
            self.states.end(job_id, "canceled", finished_at=time.time())
        except SceneError as e:
            log.error("job %s: scene %r failed to load: %s", job_id, rec.scene, e)
            self.states.end(job_id, "failed", error=self._redact(str(e)),
                            finished_at=time.time())
        except Exception as e:
            if _shards_lost(e) and self.states.requeue(job_id, self.settings.max_job_retries, e):
                return True
            log.exception("job %s failed", job_id)
            self.states.end(job_id, "failed", error=self._redact(f"{type(e).__name__}: {e}"),
                            finished_at=time.time())
        return False

    def _check_accuracy(self, scene, settings: RenderSettings, result) -> None:
        """The exact check of a proxy job's error (render() defers it when it is handed a
        renderer): scattered blocks rendered exactly on a warm pool, after the job's pool
        is back in the registry."""
        acc = result.info.get("accuracy")
        if not isinstance(acc, dict) or acc.get("check") != "deferred":
            return
        from nprt.proxies.check import run_check

        try:
            result.info["accuracy"] = run_check(scene, settings, result.film, acc,
                                                self.settings.ray_address,
                                                self.settings.proxies_dir,
                                                pools=self.sched.pools)
        except Exception as e:  # the image is done: a check that fails says so, the job stands
            log.exception("accuracy check failed")
            result.info["accuracy"] = {**acc, "check": f"failed: {type(e).__name__}: {e}"}

    def _frames(self, rec: JobRecord, job_dir: Path, settings: RenderSettings,
                live: LiveJob, scene, renderer):
        """Each frame of rec.frames on one renderer (nprt.workers.frames), each stored as
        frames/NNNNN.png and .exr. A job resumed after a restart skips the frames stored
        and re-renders the one it was in. Returns the last frame's RenderResult."""
        from nprt.scene.animation import frame_range

        frames = frame_range(f"{rec.frames[0]}:{rec.frames[1]}", scene.frames)
        per = count_passes(settings)
        checkpoint.clear_checkpoint(job_dir)  # a frame's partial film is not resumed
        todo = [f for f in frames if not checkpoint.frame_file(job_dir, f, "exr").exists()]
        (job_dir / "frames").mkdir(exist_ok=True)
        result, walls = None, {}

        def on_pass(f: int, p: PassDone) -> None:
            self.on_pass(rec.id, job_dir, live, p, (f - frames[0]) * per, rec.passes_total)

        # Every frame was stored before a restart: the last one again, for the final image.
        for done in render_frames(scene, settings, todo or [frames[-1]], on_pass=on_pass,
                                  cancel=live.cancel, renderer=renderer):
            img = done.result.film.image()
            checkpoint.atomic_write_bytes(checkpoint.frame_file(job_dir, done.frame, "png"),
                                          images.png_bytes(img))
            checkpoint.atomic_write_bytes(checkpoint.frame_file(job_dir, done.frame, "exr"),
                                          images.exr_bytes(img))
            walls[str(done.frame)] = round(done.wall_s, 4)
            log.info("job %s: frame %d done in %.2f s", rec.id, done.frame, done.wall_s)
            result = done.result
        result.info.pop("frame", None)
        result.info["passes"] = per * len(frames)
        result.info["frames"] = {"first": frames[0], "last": frames[-1], "frame_wall_s": walls}
        return result

    def checkpoint(self, job_dir: Path, live: LiveJob) -> None:
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

    def on_pass(self, job_id: str, job_dir: Path, live: LiveJob, p: PassDone, base: int = 0,
                total: int | None = None) -> None:
        """After each pass: a tile event; every checkpoint_interval_s a checkpoint (the
        partial image API workers serve) and a progress write. base, total: passes of the
        frames before this one, and of the whole job (frames jobs)."""
        total = total or p.total
        live.film, live.progress, live.stats = p.film, p.progress, p.stats
        now = time.monotonic()
        if now - live.saved_at >= self.settings.checkpoint_interval_s:
            self.checkpoint(job_dir, live)
        if now - live.stored_at >= min(1.0, self.settings.checkpoint_interval_s):
            self.store.update(job_id, passes_done=base + p.progress.count,
                              stats=p.stats.to_dict())
            live.stored_at = now
        publish_tile(self.store, job_id, p, base, total)

    def _finish(self, job_id: str, job_dir: Path, result, live: LiveJob) -> None:
        if self.store.get(job_id).cancel_requested:  # canceled during the last pass
            self.states.end(job_id, "canceled", finished_at=time.time())
            log.info("job %s canceled during its last pass; no image stored", job_id)
            return
        film = result.film
        img = film.image()
        (job_dir / "image.png").write_bytes(images.png_bytes(img))
        (job_dir / "image.exr").write_bytes(images.exr_bytes(img))
        stats = result.stats_dict()
        stats["checkpoint_bytes"] = live.checkpoint_bytes
        checkpoint.atomic_write_bytes(job_dir / "stats.json",
                                      json.dumps(stats, indent=1, default=str).encode())
        # The final film stays on disk: it proves every pixel got its samples.
        checkpoint.atomic_save_npy(job_dir / "sums.npy", film.sums)
        checkpoint.atomic_save_npy(job_dir / "samples.npy", film.samples)
        pixel_samples = {"min": int(film.samples.min()), "max": int(film.samples.max())}
        state = self.states.end(job_id, "succeeded", finished_at=time.time(),
                                stats=json.loads(json.dumps(stats, default=str)),
                                pixel_samples=pixel_samples, passes_done=result.info["passes"])
        checkpoint.clear_checkpoint(job_dir)
        log.info("job %s %s in %.2f s", job_id, state or "finished already",
                 result.info.get("wall_s", 0.0))

    def _redact(self, message: str) -> str:
        return redact_paths(message, self._roots)

    def _check_cancel(self, job_id: str, live: LiveJob, stage: str) -> None:
        """RenderCanceled if a cancel is stored: read from the store itself at these
        stage boundaries, so one stored before a stage ends is never missed between two
        polls of the scheduler."""
        if live.cancel.is_set() or self.store.get(job_id).cancel_requested:
            live.cancel.set()
            raise RenderCanceled(f"canceled while {stage}")


def _shards_lost(exc: BaseException) -> bool:
    """Whether a render failed because Ray lost its shards (a node died), not by a bug."""
    import sys

    # never imported: no shards to lose
    coordinator = sys.modules.get("nprt.workers.runtime.coordinator")
    return coordinator is not None and isinstance(exc, coordinator.ShardsLost)
