"""The one entry point that the CLI, REST and gRPC use: render a scene pass by pass,
reporting each finished pass, resumable from any pass boundary, cancellable."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from scene.model import Scene
from workers.film import Film
from workers.passes import Pass, plan_passes
from workers.settings import RenderSettings
from workers.stats import RenderStats

log = logging.getLogger(__name__)


class RenderCanceled(Exception):
    """Raised by render() when its cancel event is set between passes."""


@dataclass
class ResumeState:
    """What a render needs to go on after pass `next_pass - 1`: the film sums so far."""

    next_pass: int
    sums: np.ndarray  # (h * w, 3) float64
    samples: np.ndarray  # (h * w,) int64
    stats: dict = field(default_factory=dict)


@dataclass
class PassDone:
    index: int
    total: int
    pass_: Pass
    film: Film
    stats: RenderStats


@dataclass
class RenderResult:
    film: Film
    stats: RenderStats
    info: dict  # scene summary, partition, proxy plan, wall time

    def stats_dict(self) -> dict:
        return {**self.info, **self.stats.to_dict()}


def make_renderer(scene: Scene, settings: RenderSettings, ray_address: str | None = None,
                  proxy_dir=None):
    """The reference renderer for shards == 0, else the distributed coordinator."""
    if settings.shards == 0:
        from workers.reference import ReferenceRenderer

        return ReferenceRenderer(scene, settings)
    from workers.coordinator import Coordinator

    return Coordinator(scene, settings, ray_address=ray_address, proxy_dir=proxy_dir)


def render(scene: Scene, settings: RenderSettings, *,
           on_pass: Callable[[PassDone], None] | None = None,
           resume: ResumeState | None = None,
           cancel: threading.Event | None = None,
           ray_address: str | None = None,
           proxy_dir=None,
           renderer=None) -> RenderResult:
    """Render every pass in order; `on_pass` sees the film after each one."""
    t0 = time.perf_counter()
    passes = plan_passes(settings)
    film = Film(settings.width, settings.height)
    stats = RenderStats()
    start = 0
    if resume is not None:
        start = resume.next_pass
        film.sums[:] = resume.sums
        film.samples[:] = resume.samples
        stats = RenderStats.from_dict(resume.stats)
    own = renderer is None
    renderer = renderer or make_renderer(scene, settings, ray_address, proxy_dir)
    try:
        for p in passes[start:]:
            if cancel is not None and cancel.is_set():
                raise RenderCanceled(f"canceled before pass {p.index} of {len(passes)}")
            sums, pass_stats = renderer.run_pass(p)
            pix = p.pixels(settings.width)
            film.sums[pix] += sums
            film.samples[pix] += p.sample1 - p.sample0
            stats.merge(pass_stats)
            if on_pass is not None:
                on_pass(PassDone(p.index, len(passes), p, film, stats))
        info = dict(renderer.info())
    finally:
        if own:
            renderer.close()
    info["wall_s"] = round(time.perf_counter() - t0, 4)
    info["passes"] = len(passes)
    info["settings"] = settings.model_dump()
    return RenderResult(film, stats, info)
