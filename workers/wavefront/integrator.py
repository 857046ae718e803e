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
from nprt.workers.kernels import shade as shade_kernels
from nprt.workers.kernels.rng import DIM_BSDF_V, uniform_rows
from nprt.workers.passes import Pass
from nprt.workers.settings import RenderSettings
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.batch import (
    LIGHT_BASE,
    NO_HIT,
    ORIGIN_DTYPE,
    PRIMARY,
    SECONDARY,
    RayBatch,
    ShadowRayBatch,
)
from nprt.workers.wavefront.camera import generate_primary
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
    n = len(pixel)
    return RayBatch(
        origin=np.asarray(origin, ORIGIN_DTYPE), direction=np.asarray(direction, np.float32),
        tmax=np.full(n, INF_T, np.float32), throughput=np.asarray(throughput, np.float32),
        pixel=pixel.astype(np.uint32), sample=sample.astype(np.uint32),
        depth=depth.astype(np.uint8), kind=np.full(n, kind, np.uint8),
        visited=np.zeros(n, np.uint64), pdf_prev=np.asarray(pdf_prev, np.float32),
        hit_inst=np.full(n, NO_HIT, np.int32), hit_prim=np.full(n, -1, np.int32),
        hit_u=np.zeros(n, np.float32), hit_v=np.zeros(n, np.float32),
        hops=np.zeros(n, np.uint8), flags=np.zeros(n, np.uint8))


class PathIntegrator:
    """meshes : the base meshes held here (index -> Mesh); others cannot be shaded here."""

    def __init__(self, settings: RenderSettings, camera: Camera, meshes: Mapping[int, Mesh],
                 materials: Sequence[Material], table: InstanceTable, lights: LightSet):
        self.s, self.camera, self.meshes, self.materials = settings, camera, meshes, materials
        self.table, self.lights = table, lights
        self._lights_cache = None
        self._surfaces: SurfaceTables | None = None  # built on first use

    def primary(self, p: Pass) -> RayBatch:
        """Camera rays of one pass: every pixel of the tile times every sample of the chunk."""
        pix = p.pixels(self.s.width)
        samples = np.arange(p.sample0, p.sample1, dtype=np.uint32)
        return self.camera_rays(np.repeat(pix, len(samples)), np.tile(samples, len(pix)))

    def camera_rays(self, pixel: np.ndarray, sample: np.ndarray) -> RayBatch:
        """The camera rays of (pixel, sample) pairs, (n,) uint32 each: a function of them
        and the seed only, so any shard makes the same rays."""
        o, d = generate_primary(self.camera, self.s.width, self.s.height, self.s.seed,
                                pixel, sample)
        n = len(pixel)
        return new_rays(o, d, np.ones((n, 3)), pixel, sample, np.zeros(n, np.uint8),
                        PRIMARY, np.zeros(n))

    def shade(self, rays: RayBatch) -> Shaded:
        """Rays whose hit record (tmax, hit_inst, hit_prim, hit_u, hit_v) is final."""
        pix_parts, rgb_parts = [], []
        thr = rays.throughput.astype(np.float64)
        escaped = rays.hit_inst == NO_HIT
        if escaped.any():
            pix_parts.append(rays.pixel[escaped])
            rgb_parts.append(thr[escaped] * self.lights.environment_radiance(
                rays.direction[escaped]))
        on_light = rays.hit_inst <= LIGHT_BASE
        if on_light.any():
            pix_parts.append(rays.pixel[on_light])
            rgb_parts.append(thr[on_light] * self._light_emission(rays.take(on_light)))
        surf = np.flatnonzero(rays.hit_inst >= 0)  # (h,) rays that hit an instance
        shadow, secondary = ShadowRayBatch.empty(), RayBatch.empty()
        if len(surf):
            sf = self._surface_at(rays, surf)
            t = thr[surf]
            if sf.emission.any():
                pix_parts.append(rays.pixel[surf])
                rgb_parts.append(t * sf.emission)
            go = rays.depth[surf] < self.s.bounces
            if go.any():
                shadow = self._next_event(rays, surf, sf, t, go)
                secondary = self._continue(rays, surf, sf, t, go)
        if pix_parts:
            pixel, rgb = np.concatenate(pix_parts), np.concatenate(rgb_parts)
        else:
            pixel, rgb = np.zeros(0, np.uint32), np.zeros((0, 3))
        return Shaded(pixel, rgb, shadow, secondary)

    def _surface_at(self, rays: RayBatch, surf: np.ndarray):
        """Surfaces of rays[surf], through the kernel."""
        if self._surfaces is None:
            self._surfaces = SurfaceTables(self.meshes, self.materials, self.table)
        return self._surfaces.at(rays.hit_inst, rays.hit_prim, rays.hit_u, rays.hit_v,
                                 rays.direction, rows=surf)

    def _light_emission(self, r: RayBatch) -> np.ndarray:
        """(n, 3) f64 quad radiance, MIS-weighted against next-event sampling."""
        light = LIGHT_BASE - r.hit_inst  # (n,) light index
        le = self.lights.quad_radiance[light]
        pdf_b = r.pdf_prev.astype(np.float64)
        if self.s.shadow_rays == 0:
            return le
        pdf_l = self.s.shadow_rays * self.lights.pdf_quad_hit(light, r.tmax, r.direction)
        w = np.where(pdf_b > 0, pdf_b / (pdf_b + pdf_l), 1.0)  # camera rays: no MIS
        return le * w[:, None]

    def _next_event(self, rays: RayBatch, surf: np.ndarray, sf, thr: np.ndarray,
                    go: np.ndarray) -> ShadowRayBatch:
        """S shadow rays per hit where go; hit i is rays[surf[i]]."""
        S = self.s.shadow_rays
        if S == 0 or self.lights.count == 0:
            return ShadowRayBatch.empty()
        k, origin, wi, tmax, contrib, pix = shade_kernels.next_event(
            self.s.seed, S, np.flatnonzero(go), surf, rays.pixel, rays.sample, rays.depth,
            sf.p, sf.p_err, sf.ns, sf.ng, sf.albedo, thr, *self._light_arrays(),
            float(FAR_T), float(SHADOW_TMAX_SCALE))
        return ShadowRayBatch(
            origin=origin[:k], direction=wi[:k], tmax=tmax[:k],
            contribution=contrib[:k], pixel=pix[:k],
            visited=np.zeros(k, np.uint64), hops=np.zeros(k, np.uint8))

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

    def _continue(self, rays: RayBatch, surf: np.ndarray, sf, thr: np.ndarray,
                  go: np.ndarray) -> RayBatch:
        """One BSDF ray per hit where go (absorbed or terminated ones dropped)."""
        g = np.flatnonzero(go)
        u2 = uniform_rows(self.s.seed, surf[g], rays.pixel, rays.sample,
                                        rays.depth, DIM_BSDF_V)
        phi = 2.0 * np.pi * u2  # sines in numpy: its SIMD versions need not round like libm's
        c, k, origin, d, t, pdf = shade_kernels.bsdf_continue(
            self.s.seed, g, surf, rays.pixel, rays.sample, rays.depth, np.cos(phi),
            np.sin(phi), sf.p, sf.p_err, sf.ng, sf.ns, sf.albedo, thr, self.s.russian_roulette,
            RR_START_DEPTH)
        k = surf[k[:c]]
        return new_rays(origin[:c], d[:c], t[:c], rays.pixel[k],
                        rays.sample[k], rays.depth[k] + 1, SECONDARY, pdf[:c])
