"""Rendering the frames of an animated scene on one renderer: the reference or one warm
shard pool, started once. Between frames only the instance table and lights change, so no
mesh is reloaded and no proxy retrained (proxies are keyed by mesh content)."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from nprt.scene.model import Scene
from nprt.workers.render import PassDone, RenderResult, make_renderer, render
from nprt.workers.settings import RenderSettings


@dataclass
class FrameDone:
    frame: int
    result: RenderResult
    wall_s: float  # this frame, from its instance table swap to its last pass


def render_frames(scene: Scene, settings: RenderSettings, frames: Iterable[int], *,
                  on_pass: Callable[[int, PassDone], None] | None = None,
                  cancel: threading.Event | None = None,
                  ray_address: str | None = None, proxy_dir=None, pools=None,
                  renderer=None) -> Iterator[FrameDone]:
    """Yield each frame's render in order. `scene` is the animated scene (any frame of
    it); the renderer is made once for it (or given) and shown each frame in turn."""
    own = renderer is None
    renderer = renderer or make_renderer(scene, settings, ray_address, proxy_dir, pools)
    try:
        for f in frames:
            t0 = time.perf_counter()
            at = scene.at_frame(f)
            renderer.set_frame(at)
            hook = None if on_pass is None else (lambda done, f=f: on_pass(f, done))
            res = render(at, settings, on_pass=hook, cancel=cancel, renderer=renderer)
            res.info["frame"] = f
            yield FrameDone(f, res, time.perf_counter() - t0)
    finally:
        if own:
            renderer.close()


def frame_path(pattern: str, frame: int) -> str:
    """The output name of `frame`: the last run of '#' in pattern replaced by the frame
    number zero-padded to its length ('out_####.png', 7 -> 'out_0007.png'); a pattern
    without '#' gets '_####' before its extension."""
    runs = list(re.finditer(r"#+", pattern))
    if not runs:
        stem, dot, ext = pattern.rpartition(".")
        return f"{stem}_{frame:04d}.{ext}" if dot else f"{pattern}_{frame:04d}"
    m = runs[-1]
    return pattern[:m.start()] + f"{frame:0{len(m.group())}d}" + pattern[m.end():]
