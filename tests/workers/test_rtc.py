"""Embree's C API from compiled code (`nprt.workers.traversal.rtc`,
`nprt.workers.kernels.crossings`) answers exactly as
embreex does on the same triangles, ties on shared edges and vertices included."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from nprt.scene.demos.family import family_meshes
from nprt.workers.kernels import crossings
from nprt.workers.traversal import rtc
from nprt.workers.traversal.geometry import MeshGeometry


@njit
def _closest_all(fn, scene, o, d, tfar):
    rh, ri, ptr = crossings._scratch()
    n = o.shape[0]
    t, prim = np.empty(n, np.float32), np.empty(n, np.int32)
    u, v = np.empty(n, np.float32), np.empty(n, np.float32)
    for i in range(n):
        t[i], prim[i], u[i], v[i] = crossings.closest1(fn, scene, ptr, rh, ri, o[i, 0],
                                                       o[i, 1], o[i, 2], d[i, 0], d[i, 1],
                                                       d[i, 2], tfar[i])
    return t, prim, u, v


@njit
def _occluded_all(fn, scene, o, d, tfar):
    rh, ri, ptr = crossings._scratch()
    out = np.empty(o.shape[0], np.bool_)
    for i in range(o.shape[0]):
        out[i] = crossings.occluded1_ray(fn, scene, ptr, rh, ri, o[i, 0], o[i, 1], o[i, 2],
                                         d[i, 0], d[i, 1], d[i, 2], tfar[i])
    return out


def _rays_at_shared_edges(mesh, rng, n: int):
    """(n, 3) float32 origins around the mesh and unit directions aimed at its vertices and
    edge midpoints, where triangles sharing them tie."""
    o = (mesh.vertices.mean(0) + rng.normal(size=(n, 3)) * 3).astype(np.float32)
    f = mesh.faces[rng.integers(0, len(mesh.faces), n)]
    a, b = mesh.vertices[f[:, 0]], mesh.vertices[f[:, 1]]
    aim = np.where(rng.random((n, 1)) < 0.5, a, 0.5 * (a.astype(np.float64) + b))
    d = aim - o
    return o, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("which", [0, 2, 4])
def test_compiled_queries_equal_embreex_bit_for_bit(which):
    mesh = family_meshes("tiny")[which]
    geo = MeshGeometry(mesh)
    rng = np.random.default_rng(which)
    n = 20000
    o, d = _rays_at_shared_edges(mesh, rng, n)
    tfar = np.where(rng.random(n) < 0.3, rng.uniform(0.5, 5, n), 1e30).astype(np.float32)
    want = geo.intersect_closest(o, d, tfar)
    t, prim, u, v = _closest_all(np.uint64(rtc.INTERSECT1), geo.rtc.handle, o, d, tfar)
    hit = prim >= 0
    assert hit.mean() > 0.3
    assert np.array_equal(prim, want[1])
    assert np.array_equal(np.where(hit, t, np.inf).astype(np.float32), want[0])
    assert np.array_equal(u[hit], want[2][hit]) and np.array_equal(v[hit], want[3][hit])
    assert np.array_equal(_occluded_all(np.uint64(rtc.OCCLUDED1), geo.rtc.handle, o, d, tfar),
                          geo.intersect_occluded(o, d, tfar))


def test_scene_refuses_bad_shapes():
    with pytest.raises(ValueError, match="faces"):
        rtc.RtcScene(np.zeros((3, 3)), np.zeros((1, 4), np.uint32))


@pytest.mark.parametrize("which", [0, 2, 4])
def test_a_tfar_beyond_the_hit_by_the_margin_reports_the_hit_traced_without_a_limit(which):
    # The closest-hit walk hands Embree the closest hit so far stretched by TFAR_MARGIN_REL,
    # not FAR_T: the hit it then reports at or before that one must be the same triangle,
    # t, u and v, ties on shared edges and vertices included (rays aimed at them).
    mesh = family_meshes("tiny")[which]
    geo = MeshGeometry(mesh)  # held: it owns the Embree scene
    scene = geo.rtc.handle
    rng = np.random.default_rng(10 + which)
    n = 20000
    o, d = _rays_at_shared_edges(mesh, rng, n)
    fn = np.uint64(rtc.INTERSECT1)
    t, prim, u, v = _closest_all(fn, scene, o, d, np.full(n, 1e30, np.float32))
    hit = prim >= 0
    assert hit.mean() > 0.3
    t64 = t[hit].astype(np.float64)
    for stretch in (crossings.TFAR_MARGIN_REL, 0.01, 1.0):
        tfar = np.full(n, 1e30, np.float32)
        tfar[hit] = (t64 * (1.0 + stretch)).astype(np.float32)
        got = _closest_all(fn, scene, o, d, tfar)
        for want_col, got_col in zip((t, prim, u, v), got, strict=True):
            assert np.array_equal(want_col[hit], got_col[hit]), f"stretch {stretch}"
