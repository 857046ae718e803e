"""The single-process reference renderer: all geometry in one process, no Ray.
Every distributed image is compared against this one."""

from __future__ import annotations

import numpy as np

from scene.model import Scene
from workers.batch import KIND_NAMES, SHADOW
from workers.geometry import MeshGeometry
from workers.integrator import PathIntegrator
from workers.lights import LightSet
from workers.local import LocalGeometry
from workers.passes import Pass
from workers.settings import RenderSettings
from workers.stats import RenderStats
from workers.toplevel import InstanceTable
from workers.tracer import resolve_closest, unoccluded


class ReferenceRenderer:
    def __init__(self, scene: Scene, settings: RenderSettings):
        self.scene, self.s = scene, settings
        self.table = InstanceTable(scene)
        self.lights = LightSet(scene)
        geometry = {i: MeshGeometry(m) for i, m in enumerate(scene.meshes)}
        self.geometry = LocalGeometry(geometry, self.table, np.arange(len(scene.instances)))
        self.integrator = PathIntegrator(settings, scene.camera, dict(enumerate(scene.meshes)),
                                         scene.materials, self.table, self.lights)

    def __repr__(self) -> str:
        return f"ReferenceRenderer({self.scene.name!r}, {self.geometry})"

    def run_pass(self, p: Pass) -> tuple[np.ndarray, RenderStats]:
        """Trace one pass. Returns tile sums (p.n_pixels, 3) float64 and its statistics."""
        stats = RenderStats()
        sums = np.zeros((p.n_pixels, 3))
        w = self.s.width

        def splat(pixel, rgb):
            idx = p.local_index(pixel, w)
            for c in range(3):
                sums[:, c] += np.bincount(idx, weights=rgb[:, c], minlength=p.n_pixels)

        with stats.phase("generate"):
            rays = self.integrator.primary(p)
        while len(rays):
            stats.count_rays(rays.kind)
            with stats.phase("intersect"):
                rays = resolve_closest(rays, self.geometry, self.lights)
            with stats.phase("shade"):
                shaded = self.integrator.shade(rays)
            splat(shaded.pixel, shaded.rgb)
            shadow = shaded.shadow
            if len(shadow):
                stats.count_rays(SHADOW, len(shadow))
                with stats.phase("shadow"):
                    free = unoccluded(shadow, self.geometry)
                splat(shadow.pixel[free], shadow.contribution[free].astype(np.float64))
            rays = shaded.secondary
        stats.counters["paths"] += p.n_paths
        return sums, stats

    def info(self) -> dict:
        return {"scene": self.scene.summary(), "renderer": "reference",
                "ray_kinds": list(KIND_NAMES)}

    def close(self) -> None:
        pass
