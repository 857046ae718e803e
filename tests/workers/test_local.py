"""Two-level intersection (LocalGeometry): many instances of one base mesh along a ray."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.model import Instance, Mesh, Scene
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.traversal.toplevel import InstanceTable
from tests.workers import oracles
from tests.workers.helpers import trs

# One triangle in the x = 0 plane covering y + z <= 1 of the unit square; its box is the
# whole square, so a ray along +x crosses the box of every instance below.
TRI = Mesh("tri", np.array([[0, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32),
           np.array([[0, 1, 2]], np.uint32))
LOWER = trs((3.0, 0.0, 0.0))  # covers y + z <= 1 at x = 3
UPPER = trs((6.0, 1.0, 1.0), 1.0, (1, 0, 0), 180.0)  # covers y + z >= 1 at x = 6

# Ray a (y, z) = (0.1, 0.1) is blocked by LOWER only; ray b (0.9, 0.9) by UPPER only;
# ray c is a's line cut short before x = 3, so nothing blocks it.
ORIGIN = np.array([[0.0, 0.1, 0.1], [0.0, 0.9, 0.9], [0.0, 0.1, 0.1]], np.float32)
DIRECTION = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (3, 1))
TMAX = np.array([10.0, 10.0, 2.0], np.float32)


def _local(transforms):
    scene = Scene((TRI,), tuple(Instance(0, x) for x in transforms))
    table = InstanceTable(scene)
    return LocalGeometry({0: MeshGeometry(TRI)}, table, np.arange(len(transforms)))


@pytest.mark.parametrize("order", ["lower_first", "upper_first"])
def test_occlusion_by_one_instance_is_not_undone_by_another_of_the_same_mesh(order):
    # Each ray is paired with both instances of the same mesh and blocked by exactly one.
    # With duplicate ray indices, `occluded[r] |= hits` keeps only the last pair's answer.
    geo = _local([LOWER, UPPER] if order == "lower_first" else [UPPER, LOWER])
    occluded = geo.intersect_occluded(ORIGIN, DIRECTION, TMAX)
    assert occluded.tolist() == [True, True, False], f"occluded = {occluded.tolist()}"


@pytest.mark.parametrize("order", ["lower_first", "upper_first"])
def test_closest_hit_picks_the_nearest_instance_of_the_same_mesh(order):
    lower, upper = (0, 1) if order == "lower_first" else (1, 0)
    geo = _local([LOWER, UPPER] if order == "lower_first" else [UPPER, LOWER])
    t, inst, prim, _, _ = geo.intersect_closest(ORIGIN, DIRECTION, TMAX)
    assert inst.tolist() == [lower, upper, -1], f"inst = {inst.tolist()}"
    np.testing.assert_allclose(t[:2], [3.0, 6.0], rtol=1e-6)
    assert t[2] == TMAX[2] and prim[2] == -1


def _rays_through_overlapping_trees(n: int, seed: int):
    """An overlapping family scene's LocalGeometry and n random rays inside its patch."""
    from nprt.scene.demos.family import build

    scene = build("tiny", seed)
    table = InstanceTable(scene)
    geo = LocalGeometry({i: MeshGeometry(m) for i, m in enumerate(scene.meshes)}, table,
                        np.arange(len(table), dtype=np.int32))
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(0.05, 4, n), rng.uniform(-5, 5, n)])
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(0.5, 6, n), np.inf).astype(np.float32)
    return geo, o, d, tmax


@pytest.fixture(params=["flat", "bvh"])
def walk(request, monkeypatch):
    """The walking kernels' top level: every box in one flat loop, or the BVH (a scene
    with more boxes than FLAT_WALK_MAX)."""
    from nprt.workers.traversal import toplevel

    monkeypatch.setattr(toplevel, "FLAT_WALK_MAX", 10**9 if request.param == "flat" else 0)
    return request.param


def test_closest_hit_equals_tracing_every_crossing_with_embreex(walk):
    # The oracle traces every box crossing (culled only by tmax) through embreex, one call
    # per crossing's mesh with tfar = inf, and picks each ray's (t, instance) first. The
    # renderer gathers the boxes a ray crosses (flat loop or top-level BVH), traces them
    # through Embree's C API nearest first, with the closest hit so far (stretched) as
    # tfar, and stops once boxes are entered beyond it: the same answer bit for bit.
    from nprt.workers.traversal.local import BOX_TMAX_SLACK_REL

    geo, o, d, tmax = _rays_through_overlapping_trees(20000, 3)
    assert geo._walk()[3] == (walk == "bvh")
    t, inst, prim, u, v = geo.intersect_closest(o, d, tmax)
    ray, cross, _, _ = geo.table.box_entries(o, d, tmax.astype(np.float64)
                                             * (1.0 + BOX_TMAX_SLACK_REL), geo.instances)
    lo, ld = oracles.to_local(geo.table, cross, o[ray], d[ray])
    ht, hp = np.full(len(ray), np.inf, np.float32), np.full(len(ray), -1, np.int32)
    hu, hv = np.zeros(len(ray), np.float32), np.zeros(len(ray), np.float32)
    mesh = geo.table.mesh[cross]
    for m in np.unique(mesh):
        k = mesh == m
        ht[k], hp[k], hu[k], hv[k] = geo.geometry[m].intersect_closest(
            lo[k], ld[k], np.full(k.sum(), np.inf, np.float32))
    hit = (hp >= 0) & (ht <= tmax[ray])
    r, ht, hc, hp, hu, hv = ray[hit], ht[hit], cross[hit], hp[hit], hu[hit], hv[hit]
    order = np.lexsort((hc, ht, r))
    first = order[np.r_[True, r[order][1:] != r[order][:-1]]] if len(order) else order
    want_inst = np.full(len(o), -1, np.int32)
    want_t = tmax.copy()
    want_inst[r[first]], want_t[r[first]] = hc[first], ht[first]
    assert (want_inst >= 0).mean() > 0.2, "too few hits to compare"
    assert np.array_equal(inst, want_inst), f"{(inst != want_inst).sum()} rays differ"
    assert np.array_equal(t, want_t)
    got = inst >= 0
    assert np.array_equal(prim[got], hp[first][np.argsort(r[first])])
    assert np.array_equal(u[got], hu[first][np.argsort(r[first])])
    assert np.array_equal(v[got], hv[first][np.argsort(r[first])])


def test_occlusion_equals_tracing_every_crossing_with_embreex(walk):
    geo, o, d, tmax = _rays_through_overlapping_trees(20000, 4)
    assert geo._walk()[3] == (walk == "bvh")
    ray, cross, _, _ = geo.table.box_entries(o, d, tmax, geo.instances)
    lo, ld = oracles.to_local(geo.table, cross, o[ray], d[ray])
    blocked = np.zeros(len(ray), bool)
    mesh = geo.table.mesh[cross]
    for m in np.unique(mesh):
        k = mesh == m
        blocked[k] = geo.geometry[m].intersect_occluded(lo[k], ld[k], tmax[ray[k]])
    want = np.zeros(len(o), bool)
    want[ray[blocked]] = True
    assert 0.05 < want.mean() < 0.95
    assert np.array_equal(geo.intersect_occluded(o, d, tmax), want)
