"""Lights as arrays: quad area lights (sampled and intersectable, for MIS), point and
directional lights (sampled only), and the environment seen by escaped rays.

Next-event estimation picks one light uniformly per shadow ray; `shade_hits`
(nprt.workers.kernels.shade) gives the same density to BSDF rays that hit a quad, so both
strategies share one MIS weight.
"""

from __future__ import annotations

import numpy as np

from nprt.scene.model import Environment, Scene
from nprt.workers.kernels import quads
from nprt.workers.kernels.sampling import normalize

# "No limit" as a float32 distance: the tmax of shadow rays toward directional lights,
# and the tfar Embree traces to (nprt.workers.traversal.local).
FAR_T = np.float32(1e30)


class LightSet:
    """quad_corner, quad_u, quad_v, quad_normal (L, 3) float64, quad_area (L,) float64,
    quad_radiance (L, 3); point_pos, point_intensity (P, 3); dir_dir (unit, direction
    light travels), dir_irradiance (D, 3)."""

    def __init__(self, scene: Scene):
        def arr(items, attr, width=3):
            return np.array([getattr(x, attr) for x in items], np.float64).reshape(-1, width)

        q = scene.quad_lights
        self.quad_corner, self.quad_u, self.quad_v = (arr(q, "corner"), arr(q, "edge_u"),
                                                      arr(q, "edge_v"))
        cross = np.cross(self.quad_u, self.quad_v)
        self.quad_area = np.linalg.norm(cross, axis=1)
        self.quad_normal = normalize(cross)
        self.quad_radiance = arr(q, "radiance")
        self.point_pos = arr(scene.point_lights, "position")
        self.point_intensity = arr(scene.point_lights, "intensity")
        self.dir_dir = normalize(arr(scene.directional_lights, "direction"))
        self.dir_irradiance = arr(scene.directional_lights, "irradiance")
        self.environment: Environment = scene.environment
        self.n_quads, self.n_points = len(q), len(self.point_pos)
        self.count = self.n_quads + self.n_points + len(self.dir_dir)

    def intersect_quads(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray):
        """Closest quad hit from the emitting side within (0, tmax], t compared as the
        float32 that a hit record stores; on equal t the lower light index (the order of
        `nprt.workers.wavefront.batch.precedes`). The caller decides a tie with tmax's own hit.

        origin (n, 3) float64, direction (n, 3) float32; tmax : (n,) float32
        returns t (n,) float32 (inf if none), light (n,) int32 (-1 if none)
        """
        if self.n_quads == 0:
            n = len(origin)
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int32)
        return quads.intersect_quads(np.ascontiguousarray(origin, np.float64),
                                     np.ascontiguousarray(direction, np.float32),
                                     np.ascontiguousarray(tmax, np.float32),
                                     *self._quad_arrays())

    def _quad_arrays(self) -> tuple:
        """The quads as `quads.intersect_quads` takes them (owned and writable: arrays
        read back from Ray's object store are read-only, a separate numba type): corner,
        normal, u, v (L, 3) float64 and the squared edge lengths (L,) float64, each
        numpy's `u @ u` (made once, not pickled)."""
        made = self.__dict__.get("_quads")
        if made is None:
            made = (*(np.array(a, np.float64, order="C") for a in (
                        self.quad_corner, self.quad_normal, self.quad_u, self.quad_v)),
                    np.array([u @ u for u in self.quad_u], np.float64),
                    np.array([v @ v for v in self.quad_v], np.float64))
            self._quads = made
        return made

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_quads", None)
        return state
