"""Procedural demo scenes (forest, city, sculpture, and windy: the forest animated over 8
frames), deterministic from a seed, in three sizes:
"default" (>= 1M instanced triangles), "small" (~100k) and "tiny" (a few thousand, for tests).
"""

from __future__ import annotations

import logging
import time

from nprt.scene.demos import city, forest, sculpture, windy
from nprt.scene.errors import SceneError
from nprt.scene.model import Scene

log = logging.getLogger(__name__)

DEMOS = {"forest": forest.build, "city": city.build, "sculpture": sculpture.build,
         "windy": windy.build}
SIZES = ("default", "small", "tiny")


def make_demo(name: str, size: str = "default", seed: int = 0) -> Scene:
    """Build demo `name` at `size`; the same (name, size, seed) always gives the same scene."""
    if name not in DEMOS:
        raise SceneError(f"unknown demo {name!r}; choose one of {', '.join(DEMOS)}")
    if size not in SIZES:
        raise SceneError(f"demo {name!r}: unknown size {size!r}; choose one of {', '.join(SIZES)}")
    start = time.perf_counter()
    scene = DEMOS[name](size, int(seed))
    log.info("demo %s (%s, seed %d) built in %.2f s: %s", name, size, seed,
             time.perf_counter() - start, scene.summary())
    return scene
