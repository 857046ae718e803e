"""The jitted shading kernels against the numpy formulas they replace: bit-identical
outputs on random hits, with quad, point and directional lights mixed."""

from __future__ import annotations

import pickle
from types import SimpleNamespace as NS

import numpy as np
import pytest

from nprt.scene.demos import make_demo
from nprt.workers.kernels import shade as shade_kernels
from nprt.workers.kernels.rng import DIM_BSDF_U, DIM_BSDF_V, DIM_LIGHT_BASE, DIM_RR
from nprt.workers.kernels.sampling import normalize
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.integrator import RR_START_DEPTH, SHADOW_TMAX_SCALE, PathIntegrator
from nprt.workers.wavefront.lights import FAR_T, LightSet
from nprt.workers.wavefront.surface import SurfaceTables
from tests.workers.oracles import (
    cosine_hemisphere,
    offset_ray_origin,
    offset_rows,
    sample_lights,
    surface_at,
    uniform,
)
from tests.workers.rng_rows import uniform_rows


def _lights(rng, quads=2, points=2, dirs=1) -> LightSet:
    def v():
        return tuple(rng.normal(size=3))

    scene = NS(
        quad_lights=[NS(corner=v(), edge_u=v(), edge_v=v(), radiance=tuple(rng.random(3) * 5))
                     for _ in range(quads)],
        point_lights=[NS(position=v(), intensity=tuple(rng.random(3))) for _ in range(points)],
        directional_lights=[NS(direction=v(), irradiance=tuple(rng.random(3)))
                            for _ in range(dirs)],
        environment=NS(kind="constant", radiance=(0.1, 0.1, 0.1)))
    return LightSet(scene)


def _hits(rng, n):
    ng = normalize(rng.normal(size=(n, 3)))
    ns = normalize(ng + 0.3 * rng.normal(size=(n, 3)))
    p = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-6, 8, (n, 1))
    return NS(p=p, p_err=np.abs(p) * 1e-7 * rng.random((n, 3)), ng=ng, ns=ns,
              albedo=rng.random((n, 3)),
              thr=rng.random((n, 3)) * (rng.random((n, 1)) > 0.1),
              pixel=rng.integers(0, 1 << 20, n).astype(np.uint32),
              sample=rng.integers(0, 64, n).astype(np.uint32),
              depth=rng.integers(0, 6, n).astype(np.uint8))


def _next_event_numpy(seed, S, lights, h, go):
    """The numpy formula that PathIntegrator._next_event used before the kernel."""
    idx = np.repeat(np.flatnonzero(go), S)
    s_i = np.tile(np.arange(S), int(go.sum()))
    pix, smp, dep = h.pixel[idx], h.sample[idx], h.depth[idx]
    dim = DIM_LIGHT_BASE + 3 * s_i

    def rnd(k):
        return uniform(seed, pix, smp, dep, dim + k)

    p = h.p[idx]
    wi, dist, value, pdf_l = sample_lights(lights, rnd(0), rnd(1), rnd(2), p)
    ns, ng = h.ns[idx], h.ng[idx]
    cos_s = np.einsum("ij,ij->i", wi, ns)
    cos_g = np.einsum("ij,ij->i", wi, ng)
    pdf_b = np.maximum(cos_s, 0.0) / np.pi
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(pdf_l > 0, S * pdf_l / (S * pdf_l + pdf_b), 1.0) / S
    contrib = h.thr[idx] * (h.albedo[idx] / np.pi) * value * (np.maximum(cos_s, 0) * w)[:, None]
    ok = (cos_s > 0) & (cos_g > 0) & (contrib.max(axis=1) > 0)
    origin = offset_ray_origin(p[ok], h.p_err[idx][ok], ng[ok])
    return (origin, wi[ok].astype(np.float32), (dist[ok] * SHADOW_TMAX_SCALE).astype(np.float32),
            contrib[ok].astype(np.float32), pix[ok])


def test_uniform_rows_matches_counter_rng():
    rng = np.random.default_rng(0)
    h = _hits(rng, 5000)
    for seed, dim in ((0, 0), (12345, 7), ((1 << 63) - 1, 200)):
        want = uniform(seed, h.pixel, h.sample, h.depth, dim)
        got = uniform_rows(seed, np.arange(5000), h.pixel, h.sample, h.depth, dim)
        assert np.array_equal(want, got)


def test_next_event_kernel_matches_numpy_bit_for_bit():
    rng = np.random.default_rng(1)
    for quads, points, dirs, S in ((2, 2, 1, 4), (1, 0, 0, 1), (0, 1, 2, 3), (3, 0, 0, 2)):
        lights = _lights(rng, quads, points, dirs)
        h = _hits(rng, 3000)
        go = rng.random(3000) > 0.2
        want = _next_event_numpy(9, S, lights, h, go)
        integ = PathIntegrator.__new__(PathIntegrator)
        integ.lights, integ._lights_cache = lights, None
        k, origin, wi, tmax, con, pix = shade_kernels.next_event(
            9, S, np.flatnonzero(go), np.arange(3000), h.pixel, h.sample, h.depth, h.p,
            h.p_err, h.ns, h.ng, h.albedo, h.thr, *integ._light_arrays(), float(FAR_T),
            float(SHADOW_TMAX_SCALE))
        got = (origin[:k], wi[:k], tmax[:k], con[:k], pix[:k])
        assert k > 0
        for a, b in zip(want, got, strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)


def test_kernel_sum_orders_match_numpy():
    """The orders the kernels copy: einsum sums (p0 + p2) + p1, norm (x0² + x1²) + x2²."""
    rng = np.random.default_rng(2)
    a = rng.normal(size=(20000, 3)) * 10.0 ** rng.integers(-6, 6, (20000, 3))
    b = rng.normal(size=(20000, 3))
    p = a * b
    assert np.array_equal(np.einsum("ij,ij->i", a, b), (p[:, 0] + p[:, 2]) + p[:, 1])
    assert np.array_equal(np.linalg.norm(a, axis=1),
                          np.sqrt((a[:, 0] ** 2 + a[:, 1] ** 2) + a[:, 2] ** 2))


def _continue_numpy(seed, rr_on, h, go):
    """The numpy formula that PathIntegrator._continue used before the kernel."""
    g = np.flatnonzero(go)
    pix, smp, dep = h.pixel[g], h.sample[g], h.depth[g]
    u1 = uniform(seed, pix, smp, dep, DIM_BSDF_U)
    u2 = uniform(seed, pix, smp, dep, DIM_BSDF_V)
    d, pdf = cosine_hemisphere(u1, u2, h.ns[g])
    t = h.thr[g] * h.albedo[g]
    keep = np.einsum("ij,ij->i", d, h.ng[g]) > 0
    if rr_on:
        q = np.clip(1.0 - t.max(axis=1), 0.0, shade_kernels.RR_MAX_KILL)
        rr = dep + 1 >= RR_START_DEPTH
        survive = uniform(seed, pix, smp, dep, DIM_RR) >= q
        keep &= ~rr | survive
        t = np.where(rr[:, None], t / (1.0 - q)[:, None], t)
    keep &= t.max(axis=1) > 0
    k = g[keep]
    origin = offset_ray_origin(h.p[k], h.p_err[k], h.ng[k])
    return (k, origin, d[keep].astype(np.float32), t[keep].astype(np.float32),
            pdf[keep].astype(np.float32))


@pytest.mark.parametrize("rr_on", [False, True])
def test_continue_kernel_matches_numpy_bit_for_bit(rr_on):
    rng = np.random.default_rng(4)
    h = _hits(rng, 4000)
    h.thr[::7] = np.nan
    go = rng.random(4000) > 0.2
    want = _continue_numpy(5, rr_on, h, go)
    g = np.flatnonzero(go)
    phi = 2.0 * np.pi * uniform_rows(5, g, h.pixel, h.sample, h.depth, DIM_BSDF_V)
    c, k, origin, d, t, pdf = shade_kernels.bsdf_continue(
        5, g, np.arange(4000), h.pixel, h.sample, h.depth, np.cos(phi), np.sin(phi), h.p,
        h.p_err, h.ng, h.ns, h.albedo, h.thr, rr_on, RR_START_DEPTH)
    got = (k[:c], origin[:c], d[:c], t[:c], pdf[:c])
    assert c > 0
    for a, b in zip(want, got, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)


def _layouts(table: InstanceTable) -> dict:
    """The same table with its transforms laid out three ways in memory."""
    fortran = pickle.loads(pickle.dumps(table))
    fortran.local_to_world = np.asfortranarray(table.local_to_world)
    fortran.normal_to_world = np.asfortranarray(table.normal_to_world)
    return {"views": table, "pickled (C order)": pickle.loads(pickle.dumps(table)),
            "Fortran order": fortran}


@pytest.mark.parametrize("name", ["forest", "sculpture"])
def test_surface_kernel_matches_surface_at_bit_for_bit(name):
    """One fixed sum order, written out in surface_at, whatever the layout of the
    instance table (np.einsum's order followed the layout, so it used to be probed)."""
    scene = make_demo(name, "small")
    meshes = dict(enumerate(scene.meshes))
    rng = np.random.default_rng(6)
    n = 20000
    faces = np.array([len(m.faces) for m in scene.meshes])[scene.instance_mesh]
    inst = rng.integers(0, len(faces), n).astype(np.int32)
    prim = (rng.random(n) * faces[inst]).astype(np.int32)
    u = rng.random(n).astype(np.float32)
    v = (rng.random(n) * (1 - u)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    first = None
    for layout, table in _layouts(InstanceTable(scene)).items():
        want = surface_at(meshes, scene.materials, table, inst, prim, u, v, d)
        got = SurfaceTables(meshes, scene.materials, table).at(inst, prim, u, v, d)
        first = first or want
        for f in ("p", "ng", "ns", "albedo", "emission", "p_err"):
            assert np.array_equal(getattr(want, f), getattr(got, f)), f"{layout}: {f}"
            assert np.array_equal(getattr(want, f), getattr(first, f)), f"{layout}: {f}"


def test_surface_kernel_refuses_meshes_not_held():
    scene = make_demo("forest", "small")
    table = InstanceTable(scene)
    held = {0: scene.meshes[0]}
    other = int(np.flatnonzero(table.mesh != 0)[0])
    tables = SurfaceTables(held, scene.materials, table)
    one = np.zeros(1, np.float32)
    with pytest.raises(KeyError, match="not held"):
        tables.at(np.array([other], np.int32), np.zeros(1, np.int32), one, one,
                  np.ones((1, 3), np.float32))


def test_offset_kernel_matches_offset_ray_origin_bit_for_bit():
    """Across magnitudes, at zeros of either sign, with zero error bounds, at the float64
    extremes, and for non-finite normals."""
    rng = np.random.default_rng(7)
    n = 200000
    p = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-300, 300, (n, 3))
    p[:100] = np.array([0.0, -0.0, 1.0 / 32.0])
    p[100:200] = 1.7e308
    err = np.abs(p) * 10.0 ** rng.integers(-17, -3, (n, 3))
    err[200:300] = 0.0
    nrm = normalize(rng.normal(size=(n, 3)))
    nrm[300:400] = np.array([np.nan, np.inf, -np.inf])
    nrm[400:500] = np.array([-0.0, 0.0, 1.0])
    with np.errstate(invalid="ignore", over="ignore"):
        want = offset_ray_origin(p, err, nrm)
    got = offset_rows(p, err, nrm)
    assert np.array_equal(want.view(np.int64), got.view(np.int64))
