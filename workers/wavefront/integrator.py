"""The shading stages of the wavefront path tracer, shared by the reference renderer and
every shard: primary-ray generation, and `shade`, which turns rays with a resolved closest
hit into film contributions, next-event shadow rays and continuation rays.

Conventions (pbrt's): a ray of depth d that hits a surface adds emission; if d < bounces
the hit also does next-event estimation and spawns a depth d+1 ray. MIS (balance
heuristic, S light samples + 1 BSDF sample) applies to quad lights only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from nprt.scene.model import Camera, Material, Mesh
from nprt.workers.kernels import owned, quads
from nprt.workers.kernels import shade as shade_kernels
from nprt.workers.passes import Pass
from nprt.workers.settings import RenderSettings
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.batch import (
    NO_HIT,
    ORIGIN_DTYPE,
    PRIMARY,
    SECONDARY,
    RayBatch,
    ShadowRayBatch,
)
from nprt.workers.wavefront.camera import camera_frame
from nprt.workers.wavefront.lights import FAR_T, LightSet
from nprt.workers.wavefront.surface import SurfaceTables

RR_START_DEPTH = 3
SHADOW_TMAX_SCALE = np.float32(1.0 - 1e-4)
INF_T = np.float32(np.inf)


@dataclass(frozen=True)
class Shaded:
    """pixel (n,) u32 and rgb (n, 3) f64 film contributions, plus the rays shading made."""

    pixel: np.ndarray
    rgb: np.ndarray
    shadow: ShadowRayBatch
    secondary: RayBatch


def new_rays(origin, direction, throughput, pixel, sample, depth, kind, pdf_prev) -> RayBatch:
    """Rays that start here (no hit, no hop yet). Columns already of their dtype are taken
    as they are, not copied (batches never write their columns)."""
    n = len(pixel)
    return RayBatch(
        origin=np.asarray(origin, ORIGIN_DTYPE), direction=np.asarray(direction, np.float32),
        tmax=np.full(n, INF_T, np.float32), throughput=np.asarray(throughput, np.float32),
        pixel=np.asarray(pixel, np.uint32), sample=np.asarray(sample, np.uint32),
        depth=np.asarray(depth, np.uint8), kind=np.full(n, kind, np.uint8),
        visited=np.zeros(n, np.uint64), pdf_prev=np.asarray(pdf_prev, np.float32),
        hit_inst=np.full(n, NO_HIT, np.int32), hit_prim=np.full(n, -1, np.int32),
        hit_u=np.zeros(n, np.float32), hit_v=np.zeros(n, np.float32),
        hops=np.zeros(n, np.uint8), flags=np.zeros(n, np.uint8))


# The ray columns the shading kernels read, in `shade_kernels.shade_hits`' order first.
_SHADE_COLUMNS = ("direction", "tmax", "throughput", "pixel", "sample", "depth", "pdf_prev",
                  "hit_inst", "hit_prim", "hit_u", "hit_v")


class PathIntegrator:
    """meshes : the base meshes held here (index -> Mesh); others cannot be shaded here."""

    def __init__(self, settings: RenderSettings, camera: Camera, meshes: Mapping[int, Mesh],
                 materials: Sequence[Material], table: InstanceTable, lights: LightSet):
        self.s, self.camera, self.meshes, self.materials = settings, camera, meshes, materials
        self.table, self.lights = table, lights
        self._lights_cache = None
        self._surfaces: SurfaceTables | None = None  # built on first use
        self._frame: tuple | None = None  # the camera frame (`camera_frame`), made once
        self._env: tuple | None = None  # the environment as the kernel takes it

    def primary(self, p: Pass) -> RayBatch:
        """Camera rays of one pass: every pixel of the tile times every sample of the chunk."""
        return self.camera_rays(*self.camera_names(p))

    def camera_names(self, p: Pass) -> tuple[np.ndarray, np.ndarray]:
        """(pixel, sample) (n,) uint32 each of one pass's camera rays, in `primary`'s order."""
        pix = p.pixels(self.s.width)
        samples = np.arange(p.sample0, p.sample1, dtype=np.uint32)
        return np.repeat(pix, len(samples)), np.tile(samples, len(pix))

    def camera_rays(self, pixel: np.ndarray, sample: np.ndarray) -> RayBatch:
        """The camera rays of (pixel, sample) pairs, (n,) uint32 each: a function of them
        and the seed only, so any shard makes the same rays (`generate_primary`'s, with
        the camera frame made once)."""
        if self._frame is None:
            self._frame = camera_frame(self.camera, self.s.width, self.s.height)
        o, d = quads.camera_rays(np.uint64(self.s.seed & 0xFFFFFFFFFFFFFFFF), self.s.width,
                                 self.s.height, np.ascontiguousarray(pixel, np.uint32),
                                 np.ascontiguousarray(sample, np.uint32), *self._frame,
                                 float(self.camera.near_distance))
        n = len(pixel)
        return new_rays(o, d, np.ones((n, 3), np.float32), pixel, sample,
                        np.zeros(n, np.uint8), PRIMARY, np.zeros(n, np.float32))

    def shade(self, rays: RayBatch) -> Shaded:
        """Rays whose hit record (tmax, hit_inst, hit_prim, hit_u, hit_v) is final: film
        contributions, then S shadow rays and a BSDF ray per hit that goes on. Kernels
        throughout (`shade_kernels.shade_hits`, `surface`, `next_event`, `bsdf_continue`),
        numpy's sines between them."""
        if self._surfaces is None:
            self._surfaces = SurfaceTables(self.meshes, self.materials, self.table)
        tables, L, S = self._surfaces, self.lights, self.s.shadow_rays
        cols = {c: owned(getattr(rays, c)) for c in _SHADE_COLUMNS}
        bad, m, f_pix, f_rgb, go_ray, thr, phi = shade_kernels.shade_hits(
            self.s.seed, self.s.bounces, S, *(cols[c] for c in _SHADE_COLUMNS[:7]),
            cols["hit_inst"], *self._environment(), *self._light_arrays()[3:6], L.count,
            tables.slot_of_mesh, tables.inst_mesh, tables.mesh_mat, tables.mat_emission)
        if bad >= 0:
            tables.refuse(int(rays.hit_inst[bad]))
        shadow, secondary = ShadowRayBatch.empty(), RayBatch.empty()
        g = len(go_ray)
        if g:
            pixel, sample, depth = cols["pixel"], cols["sample"], cols["depth"]
            _, p, ng, ns, albedo, _, p_err = shade_kernels.surface(
                go_ray, cols["hit_inst"], cols["hit_prim"], cols["hit_u"], cols["hit_v"],
                cols["direction"], *tables.kernel_tables())
            hits = np.arange(g)
            if S and L.count:
                k, origin, wi, tmax, contrib, pix = shade_kernels.next_event(
                    self.s.seed, S, hits, go_ray, pixel, sample, depth, p, p_err, ns, ng,
                    albedo, thr, *self._light_arrays(), float(FAR_T), float(SHADOW_TMAX_SCALE))
                if k:
                    shadow = ShadowRayBatch(
                        origin=origin[:k], direction=wi[:k], tmax=tmax[:k],
                        contribution=contrib[:k], pixel=pix[:k],
                        visited=np.zeros(k, np.uint64), hops=np.zeros(k, np.uint8))
            c, row, origin, d, t, pdf = shade_kernels.bsdf_continue(
                self.s.seed, hits, go_ray, pixel, sample, depth, np.cos(phi), np.sin(phi), p,
                p_err, ng, ns, albedo, thr, self.s.russian_roulette, RR_START_DEPTH)
            if c:
                ray = go_ray[row[:c]]
                secondary = new_rays(origin[:c], d[:c], t[:c], pixel[ray], sample[ray],
                                     depth[ray] + 1, SECONDARY, pdf[:c])
        return Shaded(f_pix[:m], f_rgb[:m], shadow, secondary)

    def _environment(self) -> tuple:
        """The environment as `shade_kernels.shade_hits` takes it: sky or not, then
        horizon and zenith, or the constant radiance twice, (3,) float64."""
        if self._env is None:
            env = self.lights.environment
            if env.kind == "sky":
                self._env = (True, np.array(env.horizon, np.float64),
                             np.array(env.zenith, np.float64))
            else:
                rad = np.array(env.radiance, np.float64)
                self._env = (False, rad, rad)
        return self._env

    def _light_arrays(self) -> tuple:
        """The light arrays as the kernels take them: owned, writable, C-ordered float64
        (arrays read back from Ray's object store are read-only, a separate numba type)."""
        if self._lights_cache is None:
            L = self.lights
            self._lights_cache = tuple(
                np.array(a, np.float64, order="C") for a in (
                    L.quad_corner, L.quad_u, L.quad_v, L.quad_normal, L.quad_area,
                    L.quad_radiance, L.point_pos, L.point_intensity, L.dir_dir,
                    L.dir_irradiance))
        return self._lights_cache
