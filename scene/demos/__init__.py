"""Procedural demo scenes (forest, city, sculpture, and windy: the forest animated over 8
frames), deterministic from a seed, in three sizes: "default" (>= 1M instanced
triangles), "small" (~100k) and "tiny" (a few thousand, for tests), and forest in a
fourth, "massive" (nprt.scene.demos.massive). Each builder module is imported when first
built: opening a stored demo as metadata imports none (nor trimesh).
"""

from __future__ import annotations

import importlib
import logging
import time
from pathlib import Path

from nprt.scene.errors import SceneError
from nprt.scene.model import Scene

log = logging.getLogger(__name__)

DEMOS = {"forest": "nprt.scene.demos.forest", "city": "nprt.scene.demos.city",
         "sculpture": "nprt.scene.demos.sculpture",
         "windy": "nprt.scene.demos.windy"}  # name -> module with build(size, seed)
SIZES = ("default", "small", "tiny", "massive")
# "massive" (forest only: over 1 GiB of base meshes) is written once to the scene cache
# and opened as metadata (nprt.scene.store.open_scene): no process but a shard holds it whole.
DEMO_SIZES = {"forest": SIZES, "city": SIZES[:3], "sculpture": SIZES[:3],
              "windy": SIZES[:3]}


def check_demo(name: str, size: str) -> None:
    if name not in DEMOS:
        raise SceneError(f"unknown demo {name!r}; choose one of {', '.join(DEMOS)}")
    if size not in DEMO_SIZES[name]:
        raise SceneError(f"demo {name!r}: unknown size {size!r}; choose one of "
                         f"{', '.join(DEMO_SIZES[name])}")


def build_demo(name: str, size: str, seed: int, path: Path) -> Path:
    """Write demo `name` at `size` as a JSON scene at `path` (meshes as PLY beside it,
    instances in an .npz, an animation as keyframes): what
    `nprt.scene.store.materialize_demo` caches."""
    from nprt.scene.json_save import save_scene

    check_demo(name, size)
    return save_scene(make_demo(name, size, seed), path, instance_file=True)


def make_demo(name: str, size: str = "default", seed: int = 0) -> Scene:
    """Build demo `name` at `size`; the same (name, size, seed) always gives the same scene."""
    check_demo(name, size)
    start = time.perf_counter()
    scene = importlib.import_module(DEMOS[name]).build(size, int(seed))
    log.info("demo %s (%s, seed %d) built in %.2f s: %s", name, size, seed,
             time.perf_counter() - start, scene.summary())
    return scene
