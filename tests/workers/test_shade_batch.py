"""PathIntegrator.shade (kernels throughout: shade_hits, then the surface, next-event and
BSDF kernels on the hits that go on) against the numpy glue it replaced, composed as before
around the same kernels. Same film contributions (rows of zero aside: they add nothing),
same shadow and continuation rays, bit for bit, on a render's own batches with every light
type, emission, both environments, S = 0 and Russian roulette."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from nprt.scene.demos import make_demo
from nprt.scene.model import DirectionalLight, Environment, PointLight
from nprt.workers.kernels import shade as shade_kernels
from nprt.workers.kernels.rng import DIM_BSDF_V
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.batch import LIGHT_BASE, NO_HIT, SECONDARY, RayBatch, ShadowRayBatch
from nprt.workers.wavefront.integrator import (
    RR_START_DEPTH,
    SHADOW_TMAX_SCALE,
    PathIntegrator,
    new_rays,
)
from nprt.workers.wavefront.lights import FAR_T
from nprt.workers.wavefront.reference import ReferenceRenderer
from tests.workers.oracles import environment_radiance, pdf_quad_hit
from tests.workers.rng_rows import uniform_rows


def staged_shade(integ: PathIntegrator, rays: RayBatch):
    """`PathIntegrator.shade` before shade_hits: film (pixel, rgb), shadow and secondary
    batches."""
    s, lights = integ.s, integ.lights
    pix_parts, rgb_parts = [], []
    thr = rays.throughput.astype(np.float64)
    escaped = rays.hit_inst == NO_HIT
    pix_parts.append(rays.pixel[escaped])
    rgb_parts.append(thr[escaped] * environment_radiance(lights, rays.direction[escaped]))
    on_light = rays.hit_inst <= LIGHT_BASE
    r = rays.take(on_light)
    light = LIGHT_BASE - r.hit_inst
    le = lights.quad_radiance[light]
    if s.shadow_rays:
        pdf_b = r.pdf_prev.astype(np.float64)
        pdf_l = s.shadow_rays * pdf_quad_hit(lights, light, r.tmax, r.direction)
        le = le * np.where(pdf_b > 0, pdf_b / (pdf_b + pdf_l), 1.0)[:, None]
    pix_parts.append(rays.pixel[on_light])
    rgb_parts.append(thr[on_light] * le)
    surf = np.flatnonzero(rays.hit_inst >= 0)
    sf = integ._surfaces.at(rays.hit_inst, rays.hit_prim, rays.hit_u, rays.hit_v,
                            rays.direction, rows=surf)
    t = thr[surf]
    if sf.emission.any():
        pix_parts.append(rays.pixel[surf])
        rgb_parts.append(t * sf.emission)
    g = np.flatnonzero(rays.depth[surf] < s.bounces)
    shadow = ShadowRayBatch.empty()
    if s.shadow_rays and lights.count:
        k, origin, wi, tmax, contrib, pix = shade_kernels.next_event(
            s.seed, s.shadow_rays, g, surf, rays.pixel, rays.sample, rays.depth, sf.p,
            sf.p_err, sf.ns, sf.ng, sf.albedo, t, *integ._light_arrays(), float(FAR_T),
            float(SHADOW_TMAX_SCALE))
        shadow = ShadowRayBatch(origin=origin[:k], direction=wi[:k], tmax=tmax[:k],
                                contribution=contrib[:k], pixel=pix[:k],
                                visited=np.zeros(k, np.uint64), hops=np.zeros(k, np.uint8))
    phi = 2.0 * np.pi * uniform_rows(s.seed, surf[g], rays.pixel, rays.sample, rays.depth,
                                     DIM_BSDF_V)
    c, k, origin, d, tc, pdf = shade_kernels.bsdf_continue(
        s.seed, g, surf, rays.pixel, rays.sample, rays.depth, np.cos(phi), np.sin(phi),
        sf.p, sf.p_err, sf.ng, sf.ns, sf.albedo, t, s.russian_roulette, RR_START_DEPTH)
    k = surf[k[:c]]
    secondary = new_rays(origin[:c], d[:c], tc[:c], rays.pixel[k], rays.sample[k],
                         rays.depth[k] + 1, SECONDARY, pdf[:c])
    return np.concatenate(pix_parts), np.concatenate(rgb_parts), shadow, secondary


def _rows(pixel, rgb):
    """Film rows in a canonical order, rows of zero left out; rgb compared as bits."""
    keep = ~np.all(rgb == 0, axis=1)
    pixel, bits = pixel[keep], np.ascontiguousarray(rgb[keep]).view(np.int64)
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0], pixel))
    return pixel[order], bits[order]


def _same_batch(a, b) -> None:
    assert len(a) == len(b)
    for name in a._SPEC:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name


def _read_only(rays: RayBatch) -> RayBatch:
    """The batch as it arrives from Ray's object store: every column read-only."""
    cols = {}
    for name in rays._SPEC:
        a = getattr(rays, name).copy()
        a.flags.writeable = False
        cols[name] = a
    return RayBatch(**cols)


def _scene(env: Environment):
    scene = make_demo("forest", "tiny")
    mats = list(scene.materials)
    mats[0] = dataclasses.replace(mats[0], emission=(0.7, 0.2, 0.05))
    c = scene.camera.target
    return dataclasses.replace(
        scene, materials=tuple(mats), environment=env,
        point_lights=(PointLight((c[0] + 1.0, c[1] + 3.0, c[2] + 0.5), (5.0, 4.0, 3.0)),),
        directional_lights=(DirectionalLight((0.3, -1.0, 0.2), (0.8, 0.9, 1.0)),))


@pytest.mark.parametrize(("env", "shadow_rays", "rr"), [
    (Environment(kind="sky", zenith=(0.2, 0.3, 0.9), horizon=(0.9, 0.8, 0.6)), 2, True),
    (Environment(kind="constant", radiance=(0.3, 0.4, 0.5)), 1, False),
    (Environment(kind="constant", radiance=(0.3, 0.4, 0.5)), 0, True),
])
def test_shade_matches_the_staged_kernels_bit_for_bit(env, shadow_rays, rr):
    settings = RenderSettings(width=40, height=30, spp=2, bounces=4, shadow_rays=shadow_rays,
                              russian_roulette=rr, seed=5, shards=0)
    renderer = ReferenceRenderer(_scene(env), settings)
    integ = renderer.shard.integrator
    seen = []
    shade = integ.shade
    integ.shade = lambda rays: seen.append(rays) or shade(rays)
    renderer.run_pass(next(iter(_passes(settings))))
    del integ.shade
    assert len(seen) >= 3
    rng = np.random.default_rng(shadow_rays)
    last = seen[-1]
    thr = last.throughput.copy()
    thr[rng.random(len(last)) < 0.05] = np.nan  # NaN paths: dropped, their emission kept
    kinds = {tuple(np.unique(np.sign(b.hit_inst + 1))) for b in seen}
    assert {-1, 0, 1} <= set().union(*kinds)  # lights, escaped and surfaces were hit
    for rays in [*seen, last.replace(throughput=thr), _read_only(seen[1])]:
        want_pix, want_rgb, want_shadow, want_secondary = staged_shade(integ, rays)
        got = integ.shade(rays)
        for a, b in zip(_rows(want_pix, want_rgb), _rows(got.pixel, got.rgb), strict=True):
            assert np.array_equal(a, b)
        assert got.rgb.dtype == np.float64 and got.pixel.dtype == np.uint32
        _same_batch(want_shadow, got.shadow)
        _same_batch(want_secondary, got.secondary)


def _passes(settings):
    from nprt.workers.passes import iter_passes

    return iter_passes(settings)


def test_shade_refuses_a_hit_on_a_mesh_not_held():
    scene = make_demo("forest", "tiny")
    settings = RenderSettings(width=8, height=8, spp=1, shards=0)
    integ = ReferenceRenderer(scene, settings).shard.integrator
    held = PathIntegrator(settings, scene.camera, {0: scene.meshes[0]}, scene.materials,
                          integ.table, integ.lights)
    other = int(np.flatnonzero(integ.table.mesh != 0)[0])
    rays = integ.camera_rays(np.zeros(1, np.uint32), np.zeros(1, np.uint32))
    rays = rays.replace(hit_inst=np.array([other], np.int32))
    with pytest.raises(KeyError, match="not held"):
        held.shade(rays)
