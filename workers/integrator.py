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

from scene.model import Camera, Material, Mesh
from workers.batch import LIGHT_BASE, NO_HIT, PRIMARY, SECONDARY, RayBatch, ShadowRayBatch
from workers.camera import generate_primary
from workers.lights import LightSet
from workers.offset import offset_ray_origin
from workers.passes import Pass
from workers.rng import DIM_BSDF_U, DIM_BSDF_V, DIM_LIGHT_BASE, DIM_RR, uniform
from workers.sampling import cosine_hemisphere
from workers.settings import RenderSettings
from workers.surface import surface_at
from workers.toplevel import InstanceTable

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
        origin=np.asarray(origin, np.float32), direction=np.asarray(direction, np.float32),
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

    def primary(self, p: Pass) -> RayBatch:
        """Camera rays of one pass: every pixel of the tile times every sample of the chunk."""
        pix = p.pixels(self.s.width)
        samples = np.arange(p.sample0, p.sample1, dtype=np.uint32)
        pixel = np.repeat(pix, len(samples))
        sample = np.tile(samples, len(pix))
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
        surf = rays.hit_inst >= 0
        shadow, secondary = ShadowRayBatch.empty(), RayBatch.empty()
        if surf.any():
            r = rays.take(surf)
            sf = surface_at(self.meshes, self.materials, self.table, r.hit_inst, r.hit_prim,
                            r.hit_u, r.hit_v, r.direction)
            t = thr[surf]
            if sf.emission.any():
                pix_parts.append(r.pixel)
                rgb_parts.append(t * sf.emission)
            go = r.depth < self.s.bounces
            if go.any():
                shadow = self._next_event(r, sf, t, go)
                secondary = self._continue(r, sf, t, go)
        if pix_parts:
            pixel, rgb = np.concatenate(pix_parts), np.concatenate(rgb_parts)
        else:
            pixel, rgb = np.zeros(0, np.uint32), np.zeros((0, 3))
        return Shaded(pixel, rgb, shadow, secondary)

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

    def _next_event(self, r: RayBatch, sf, thr: np.ndarray, go: np.ndarray) -> ShadowRayBatch:
        S = self.s.shadow_rays
        if S == 0 or self.lights.count == 0:
            return ShadowRayBatch.empty()
        idx = np.repeat(np.flatnonzero(go), S)  # (n*S,) rows of r
        s_i = np.tile(np.arange(S), int(go.sum()))
        pix, smp, dep = r.pixel[idx], r.sample[idx], r.depth[idx]
        dim = DIM_LIGHT_BASE + 3 * s_i

        def rnd(k):
            return uniform(self.s.seed, pix, smp, dep, dim + k)

        p = sf.p[idx]
        wi, dist, value, pdf_l = self.lights.sample(rnd(0), rnd(1), rnd(2), p)
        ns, ng = sf.ns[idx], sf.ng[idx]
        cos_s = np.einsum("ij,ij->i", wi, ns)
        cos_g = np.einsum("ij,ij->i", wi, ng)
        pdf_b = np.maximum(cos_s, 0.0) / np.pi
        # Light samples carry Le/p_l; the balance weight S p_l / (S p_l + p_b) over S.
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(pdf_l > 0, S * pdf_l / (S * pdf_l + pdf_b), 1.0) / S
        contrib = thr[idx] * (sf.albedo[idx] / np.pi) * value * (np.maximum(cos_s, 0) * w)[:, None]
        ok = (cos_s > 0) & (cos_g > 0) & (contrib.max(axis=1) > 0)
        origin = offset_ray_origin(p[ok].astype(np.float32), ng[ok].astype(np.float32))
        n = int(ok.sum())
        return ShadowRayBatch(
            origin=origin, direction=wi[ok].astype(np.float32),
            tmax=(dist[ok] * SHADOW_TMAX_SCALE).astype(np.float32),
            contribution=contrib[ok].astype(np.float32), pixel=pix[ok],
            visited=np.zeros(n, np.uint64), hops=np.zeros(n, np.uint8))

    def _continue(self, r: RayBatch, sf, thr: np.ndarray, go: np.ndarray) -> RayBatch:
        g = np.flatnonzero(go)
        pix, smp, dep = r.pixel[g], r.sample[g], r.depth[g]
        u1 = uniform(self.s.seed, pix, smp, dep, DIM_BSDF_U)
        u2 = uniform(self.s.seed, pix, smp, dep, DIM_BSDF_V)
        d, pdf = cosine_hemisphere(u1, u2, sf.ns[g])
        t = thr[g] * sf.albedo[g]  # f * cos / pdf for a Lambertian BSDF
        keep = np.einsum("ij,ij->i", d, sf.ng[g]) > 0  # below the true surface: absorbed
        if self.s.russian_roulette:
            q = np.clip(1.0 - t.max(axis=1), 0.0, 0.95)
            rr = dep + 1 >= RR_START_DEPTH
            survive = uniform(self.s.seed, pix, smp, dep, DIM_RR) >= q
            keep &= ~rr | survive
            t = np.where(rr[:, None], t / (1.0 - q)[:, None], t)
        keep &= t.max(axis=1) > 0
        k = g[keep]
        origin = offset_ray_origin(sf.p[k].astype(np.float32), sf.ng[k].astype(np.float32))
        return new_rays(origin, d[keep], t[keep], r.pixel[k], r.sample[k],
                        r.depth[k] + 1, SECONDARY, pdf[keep])
