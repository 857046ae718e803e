"""The one entry point that the CLI, REST and gRPC use: render a scene pass by pass,
reporting each finished pass, resumable from any set of finished passes, cancellable."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from nprt.scene.meta import SceneMeta
from nprt.scene.model import Scene
from nprt.workers.film import Film
from nprt.workers.jitcache import note_cold_compile
from nprt.workers.passes import Pass, count_passes, iter_passes
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats

log = logging.getLogger(__name__)


class RenderCanceled(Exception):
    """Raised by render() when its cancel event is set between passes."""


@dataclass
class ResumeState:
    """What a render needs to go on: the film sums so far, and which passes they hold
    (every pass below `next_pass`, plus `done`, finished out of order above it)."""

    next_pass: int
    sums: np.ndarray  # (h * w, 3) float64
    samples: np.ndarray  # (h * w,) int64
    stats: dict = field(default_factory=dict)
    done: list[int] = field(default_factory=list)


class Progress:
    """Finished passes as a low-water mark plus the few finished above it (passes finish
    out of order, at most a window apart): O(window) memory for any number of passes."""

    def __init__(self, next_pass: int = 0, done=()):
        self.next_pass, self.done = next_pass, set(done)
        self._advance()

    def mark(self, index: int) -> None:
        self.done.add(index)
        self._advance()

    def _advance(self) -> None:
        while self.next_pass in self.done:
            self.done.discard(self.next_pass)
            self.next_pass += 1

    @property
    def count(self) -> int:
        return self.next_pass + len(self.done)


@dataclass
class PassDone:
    index: int
    total: int
    pass_: Pass
    film: Film  # read it under film.lock: other passes are added from the render thread
    stats: RenderStats
    progress: Progress


@dataclass
class RenderResult:
    film: Film
    stats: RenderStats
    info: dict  # scene summary, partition, proxy plan, wall time

    def stats_dict(self) -> dict:
        return {**self.info, **self.stats.to_dict()}


def make_renderer(scene, settings: RenderSettings, ray_address: str | None = None,
                  proxy_dir=None, pools=None, on_progress=None, trace: bool = False):
    """The reference renderer for shards == 0 (a stored scene's metadata is loaded whole
    here), else a coordinator (on a warm pool from the PoolRegistry `pools` if given).
    scene: a Scene, or a SceneMeta from nprt.scene.store.open_scene (the driver then holds no
    geometry); on_progress: per-mesh proxy training progress (Coordinator)."""
    note_cold_compile("reference render" if settings.shards == 0 else "shard warm-up",
                      distributed=settings.shards > 0, proxies=settings.mode == "proxy")
    if settings.shards == 0:
        from nprt.workers.wavefront.reference import ReferenceRenderer

        return ReferenceRenderer(scene.load() if isinstance(scene, SceneMeta) else scene,
                                 settings)
    from nprt.workers.runtime.coordinator import Coordinator

    return Coordinator(scene, settings, ray_address=ray_address, proxy_dir=proxy_dir,
                       pools=pools, on_progress=on_progress, trace=trace)


def render(scene: Scene | SceneMeta, settings: RenderSettings, *,
           on_pass: Callable[[PassDone], None] | None = None,
           resume: ResumeState | None = None,
           cancel: threading.Event | None = None,
           ray_address: str | None = None,
           proxy_dir=None,
           renderer=None) -> RenderResult:
    """Render every pass (several at once when distributed); `on_pass` sees the film after
    each one finishes, in the order they finish. The passes of one tile finish in pass
    order (a renderer keeps at most one pass per tile live), so every pixel's sums are
    added in the same order in any run, faulted or not: the film's bytes do not depend
    on timing."""
    t0 = time.perf_counter()
    total = count_passes(settings)
    film = Film(settings.width, settings.height)
    stats = RenderStats()
    progress = Progress()
    if resume is not None:
        progress = Progress(resume.next_pass, resume.done)
        film.sums[:] = resume.sums
        film.samples[:] = resume.samples
        stats = RenderStats.from_dict(resume.stats)
    own = renderer is None
    renderer = renderer or make_renderer(scene, settings, ray_address, proxy_dir)
    try:
        todo = iter_passes(settings, progress.next_pass, progress.done)
        finished = renderer.render_passes(todo, cancel)
        try:
            for p, sums, pass_stats in finished:
                pix = p.pixels(settings.width)
                with film.lock:
                    film.sums[pix] += sums
                    film.samples[pix] += p.sample1 - p.sample0
                pass_stats.counters["paths"] += p.n_paths
                stats.merge(pass_stats)
                progress.mark(p.index)
                if on_pass is not None:
                    on_pass(PassDone(p.index, total, p, film, stats, progress))
                if cancel is not None and cancel.is_set():
                    break
        finally:
            finished.close()
        if progress.count < total:
            raise RenderCanceled(f"canceled with {progress.count} of {total} passes done")
        info = dict(renderer.info())
        if settings.mode == "proxy":  # the accuracy target and the predicted error
            from nprt.proxies.check import accuracy_report

            info["accuracy"] = accuracy_report(scene, settings, renderer.plan, stats)
    finally:
        if own:
            renderer.close()
    if settings.mode == "proxy" and settings.proxy.check:
        # On a pool of its own once this one is closed; a caller that passed its renderer
        # runs nprt.proxies.check.run_check itself after closing it.
        from nprt.proxies.check import run_check

        info["accuracy"] = run_check(scene, settings, film, info["accuracy"], ray_address,
                                     proxy_dir) if own else {**info["accuracy"],
                                                             "check": "deferred"}
    info["wall_s"] = round(time.perf_counter() - t0, 4)
    info["passes"] = total
    info["settings"] = settings.model_dump()
    return RenderResult(film, stats, info)
