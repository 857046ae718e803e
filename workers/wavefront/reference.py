"""The single-process reference renderer: the wavefront of one Shard that holds the whole
scene, driven in this process without Ray. Every distributed image is compared against it,
and it runs the same stages under the same names as every shard."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from fractions import Fraction

import numpy as np

from nprt.scene.model import Scene
from nprt.workers.passes import Pass
from nprt.workers.runtime.protocol import ShardConfig
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats
from nprt.workers.wavefront.batch import KIND_NAMES
from nprt.workers.wavefront.shard import Shard
from nprt.workers.wavefront.world import ShardWorld

# Paths the reference traces in one step (several passes of distinct tiles): the batch
# glue costs a few ms a step whatever its size (foliage, 160x120x16: 4 passes a step ran
# 8 % faster than one), and much larger steps run slower (columns outgrow the caches).
STEP_PATHS = 1 << 16


class ReferenceRenderer:
    def __init__(self, scene: Scene, settings: RenderSettings):
        t0 = time.perf_counter()
        self.scene, self.s = scene, settings
        world = ShardWorld.build(scene, np.zeros(len(scene.instance_mesh), np.int32))
        self.shard = Shard(ShardConfig(0, 1, settings), world, dict(enumerate(scene.meshes)))
        self.warm_s = self.shard.warm()
        self.shard.begin(settings)
        self.prepare_s = time.perf_counter() - t0
        self.cpu_s = 0.0  # process CPU seconds spent in passes

    def set_frame(self, scene: Scene) -> None:
        """Render `scene` (a frame of this one: same meshes and instance meshes) from now on:
        only the instance table and lights change."""
        self.scene = scene
        self.shard.set_world(ShardWorld.build(scene, self.shard.world.owner))

    @property
    def geometry(self):
        """The whole scene's LocalGeometry (tests swap in an instrumented one)."""
        return self.shard.local

    @geometry.setter
    def geometry(self, value) -> None:
        self.shard.local = value

    def __repr__(self) -> str:
        return f"ReferenceRenderer({self.scene.name!r}, {self.shard.local})"

    def run_pass(self, p: Pass) -> tuple[np.ndarray, RenderStats]:
        """Trace one pass. Returns tile sums (p.n_pixels, 3) float64 and its statistics."""
        return self.run_passes([p])[0]

    def run_passes(self, group: list[Pass]) -> list[tuple[np.ndarray, RenderStats]]:
        """Trace passes of distinct tiles as one wavefront step. Returns each one's tile
        sums (n_pixels, 3) float64 and statistics, in the order given: the same as tracing
        them one by one (a pass's film is summed as exact integers, its counts by pass)."""
        c0 = time.process_time()
        whole = {p.index: Fraction(1) for p in group}
        res = self.shard.step(group, [], whole)
        if any(res.parcels) or res.returned != whole:
            raise RuntimeError(f"passes {sorted(whole)}: one shard holding everything sent "
                               "rays away")
        out = [(sums.to_float(), RenderStats.from_dict(stats))
               for _, sums, stats in self.shard.collect(list(whole))]
        self.cpu_s += time.process_time() - c0
        return out

    def render_passes(self, passes: Iterator[Pass], cancel: threading.Event | None = None):
        """Yield (pass, tile sums, stats) one pass after another, in the order given.
        Consecutive passes of distinct tiles, up to STEP_PATHS paths, run as one step."""
        group: list[Pass] = []
        for p in passes:
            if group and (sum(q.n_paths for q in group) + p.n_paths > STEP_PATHS
                          or any(q.x0 == p.x0 and q.y0 == p.y0 for q in group)):
                yield from self._yield_group(group, cancel)
                group = []
            group.append(p)
        if group:
            yield from self._yield_group(group, cancel)

    def _yield_group(self, group: list[Pass], cancel: threading.Event | None):
        if cancel is not None and cancel.is_set():
            return
        for p, (sums, st) in zip(group, self.run_passes(group), strict=True):
            yield p, sums, st

    def info(self) -> dict:
        return {"scene": self.scene.summary(), "renderer": "reference",
                "ray_kinds": list(KIND_NAMES), "prepare_s": round(self.prepare_s, 4),
                "cpu_s": round(self.cpu_s, 4)}

    def close(self) -> None:
        pass
