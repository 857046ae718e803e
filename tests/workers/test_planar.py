"""The walks skip a planar mesh (a ground quad) for a ray that leaves its plane
(`nprt.workers.traversal.planar`, `crossings._leaves_plane`): Embree must find no hit in
any such case, so the skip changes no answer."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from nprt.scene.demos import make_demo
from nprt.scene.model import Mesh
from nprt.workers.kernels import crossings
from nprt.workers.traversal import rtc
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.traversal.planar import plane_row
from nprt.workers.traversal.toplevel import InstanceTable

QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def _quad(axis: int, c: float, half: float, center=(0.0, 0.0)) -> np.ndarray:
    """(4, 3) float32 corners of a square of half-size `half` in the plane x_axis = c."""
    p, q = [a for a in range(3) if a != axis]
    v = np.zeros((4, 3), np.float32)
    v[:, axis] = c
    v[:, p] = center[0] + half * np.array([-1, 1, 1, -1])
    v[:, q] = center[1] + half * np.array([-1, -1, 1, 1])
    return v


@njit
def _leaves(planes, o, d):
    out = np.empty(o.shape[0], np.bool_)
    for i in range(o.shape[0]):
        out[i] = crossings._leaves_plane(planes, 0, o[i, 0], o[i, 1], o[i, 2], d[i, 0],
                                         d[i, 1], d[i, 2])
    return out


@njit
def _embree(fn_c, fn_o, scene, o, d):
    rh, ri, ptr = crossings._scratch()
    hit = np.empty(o.shape[0], np.bool_)
    occ = np.empty(o.shape[0], np.bool_)
    for i in range(o.shape[0]):
        _, p, _, _ = crossings.closest1(fn_c, scene, ptr, rh, ri, o[i, 0], o[i, 1], o[i, 2],
                                        d[i, 0], d[i, 1], d[i, 2], np.float32(1e30))
        hit[i] = p >= 0
        occ[i] = crossings.occluded1_ray(fn_o, scene, ptr, rh, ri, o[i, 0], o[i, 1], o[i, 2],
                                         d[i, 0], d[i, 1], d[i, 2], np.float32(1e30))
    return hit, occ


def test_plane_row_marks_only_meshes_in_one_axis_plane():
    axis, c, reach = plane_row(_quad(1, 0.0, 40.0), QUAD_FACES)
    assert (axis, c) == (1.0, 0.0) and reach >= 80.0
    assert plane_row(_quad(2, 2.5, 1.0), QUAD_FACES)[:2] == (2.0, 2.5)
    tilted = _quad(1, 0.0, 1.0)
    tilted[2, 1] = np.nextafter(np.float32(0), np.float32(1))  # one vertex a hair off
    assert plane_row(tilted, QUAD_FACES)[0] == -1.0
    sliver = _quad(0, 1.0, 1.0)
    sliver[2] = sliver[1]  # a triangle of zero area
    assert plane_row(sliver, QUAD_FACES)[0] == -1.0
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float32)
    assert plane_row(cube, np.array([[0, 1, 3], [4, 5, 7]]))[0] == -1.0  # planes x=0, x=1
    with pytest.raises(ValueError, match="vertices"):
        plane_row(np.zeros((4, 2)), QUAD_FACES)


def _rays_off_the_plane(rng, axis, c, half, n):
    """Local rays with origins a few float32 ulps to the quad's size off the plane (over
    the quad and beyond it) and directions of every magnitude, half of them toward it."""
    p, q = [a for a in range(3) if a != axis]
    o = np.empty((n, 3), np.float32)
    o[:, p] = rng.uniform(-2 * half, 2 * half, n)
    o[:, q] = rng.uniform(-2 * half, 2 * half, n)
    side = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    steps = rng.integers(1, 64, n)
    near = np.array([c], np.float32).repeat(n)
    for k in range(64):  # walk `steps` ulps away from c, on each ray's side
        moving = steps > k
        near[moving] = np.nextafter(near[moving], np.where(side > 0, np.inf, -np.inf)[moving]
                                    .astype(np.float32))
    scale = max(abs(c), half)
    off = (c + side * scale * 10.0 ** rng.uniform(-12, 0.5, n)).astype(np.float32)
    o[:, axis] = np.where(rng.random(n) < 0.4, near, off)
    d = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-6, 3, (n, 1))
    d[:, axis] = np.abs(d[:, axis]) * np.where(rng.random(n) < 0.5, 1, -1)
    grazing = rng.random(n) < 0.2
    d[grazing, axis] *= 1e-6
    return o, d.astype(np.float32)


@pytest.mark.parametrize("axis, c, half", [(1, 0.0, 40.0), (0, 2.5, 1.0), (2, -1000.25, 300.0),
                                           (1, 1e-3, 0.02)])
def test_embree_finds_no_hit_where_the_plane_skip_applies(axis, c, half):
    vertices = _quad(axis, c, half, center=(0.3 * half, -0.1 * half))
    geo = MeshGeometry(Mesh("quad", vertices, QUAD_FACES))
    planes = np.array([plane_row(vertices, QUAD_FACES)])
    assert planes[0, 0] == axis
    rng = np.random.default_rng(axis)
    o, d = _rays_off_the_plane(rng, axis, c, half, 200_000)
    skip = _leaves(planes, o, d)
    hit, occ = _embree(np.uint64(rtc.INTERSECT1), np.uint64(rtc.OCCLUDED1), geo.rtc.handle,
                       o, d)
    assert skip.mean() > 0.15, "too few rays leave the plane to test anything"
    assert hit[~skip].mean() > 0.05, "the rays toward the plane should often hit it"
    assert not hit[skip].any(), f"Embree hit {hit[skip].sum()} skipped rays"
    assert not occ[skip].any(), f"Embree occluded {occ[skip].sum()} skipped rays"
    toward = ((o[:, axis].astype(np.float64) - c) * d[:, axis]) < 0
    assert not (skip & toward).any()


def test_walks_answer_the_same_with_and_without_the_plane_skip():
    scene = make_demo("sculpture", "tiny")
    table = InstanceTable(scene)
    geo = LocalGeometry({i: MeshGeometry(m) for i, m in enumerate(scene.meshes)}, table,
                        np.arange(len(table), dtype=np.int32))
    assert (geo._mesh_planes()[:, 0] >= 0).any(), "the demo's ground should be planar"
    rng = np.random.default_rng(3)
    n = 20_000
    # Rays leaving the ground (as shadow and bounce rays do) and rays through the scene.
    o = np.column_stack([rng.uniform(-6, 6, n), np.zeros(n), rng.uniform(-6, 6, n)])
    o[:, 1] = np.where(rng.random(n) < 0.5, 1e-5 * rng.random(n), rng.uniform(-1, 3, n))
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    tmax = np.where(rng.random(n) < 0.5, rng.uniform(0.1, 8, n), np.inf).astype(np.float32)
    closest = geo.intersect_closest(o, d, tmax)
    occluded = geo.intersect_occluded(o, d, tmax)
    geo._planes = np.tile([-1.0, 0.0, 0.0], (len(geo._planes), 1))  # no skips
    want_closest = geo.intersect_closest(o, d, tmax)
    want_occluded = geo.intersect_occluded(o, d, tmax)
    for got, want in zip(closest, want_closest, strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(occluded, want_occluded)
    assert (want_closest[1] >= 0).mean() > 0.2 and want_occluded.mean() > 0.1
