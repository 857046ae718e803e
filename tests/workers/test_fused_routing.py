"""Exact routing inside the local walks: their answer (`closest_routed`, `occluded_routed`,
cut at the final tmax by `next_stop`) picks the same next shard as the separate walk it
replaced (`nearest_unvisited`) and as listing and sorting every crossing (the oracle),
and the local answers do not change, on
random rays and rays aimed at box corners, box faces and shared triangle edges, for
several shard splits and visited masks, through the flat loops and the BVH."""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import pytest

from nprt.scene.demos import make_demo
from nprt.scene.model import Instances
from nprt.workers.kernels.records import NO_HIT
from nprt.workers.routing.exact import DONE, candidate_owner, nearest_unvisited, next_stop
from nprt.workers.traversal import toplevel
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import BOX_TMAX_SLACK_REL, LocalGeometry
from nprt.workers.wavefront.world import ShardWorld
from tests.workers.oracles import nearest_by_crossings


def _aimed(world, scene, rng, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from around the scene to box corners, edge and face midpoints, and to mesh
    vertices and edge midpoints of instances (shared edges: ties of hits)."""
    b = world.table.world_bounds  # (m, 2, 3)
    lo, hi = b[:, 0].min(0), b[:, 1].max(0)
    box = rng.integers(0, len(b), n)
    pick = rng.integers(0, 3, (n, 3))  # per axis: lo, middle, hi
    mid = 0.5 * (b[box, 0] + b[box, 1])
    target = np.where(pick == 0, b[box, 0], np.where(pick == 1, mid, b[box, 1]))
    on_mesh = rng.random(n) < 0.5
    inst = rng.integers(0, len(b), n)
    for i in np.flatnonzero(on_mesh):
        mesh = scene.meshes[scene.instance_mesh[inst[i]]]
        f = mesh.faces[rng.integers(0, len(mesh.faces))]
        w = rng.integers(0, 2, 2)  # a vertex or an edge midpoint
        p = 0.5 * (mesh.vertices[f[w[0]]] + mesh.vertices[f[w[0] + w[1]]]).astype(np.float64)
        xf = world.table.local_to_world[inst[i]]
        target[i] = xf[:, :3] @ p + xf[:, 3]
    origin = rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), (n, 3))
    direction = (target - origin).astype(np.float32)
    direction[::11, rng.integers(0, 3)] = 0.0  # axis-parallel faces: zero components
    return origin, direction / np.linalg.norm(direction, axis=1, keepdims=True)


def _random(world, rng, n: int) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = world.table.world_bounds[:, 0].min(0), world.table.world_bounds[:, 1].max(0)
    origin = rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (n, 3))
    direction = rng.normal(size=(n, 3)).astype(np.float32)
    direction[::7, rng.integers(0, 3)] = 0.0
    return origin, direction / np.linalg.norm(direction, axis=1, keepdims=True)


def _cuts(world, remote, origin, direction, walk_tmax, rng) -> np.ndarray:
    """(n,) float32 final tmax at or below walk_tmax on the edge of a box entry: the
    stretched cut lands just below, on, or just above a crossing's t_enter."""
    stretch = 1.0 + BOX_TMAX_SLACK_REL
    box_tmax = walk_tmax.astype(np.float64) * stretch
    ray, _, t_enter, _ = world.table.box_entries(origin, direction, box_tmax, remote)
    cut = walk_tmax.copy()
    pick = rng.permutation(len(ray))
    cut[ray[pick]] = (t_enter[pick] / stretch).astype(np.float32)
    step = rng.integers(-1, 2, len(cut))
    cut = np.where(step < 0, np.nextafter(cut, -np.inf), np.where(step > 0,
                   np.nextafter(cut, np.inf), cut)).astype(np.float32)
    return np.minimum(cut, walk_tmax)


def _second_walk(world, remote, origin, direction, tmax, visited) -> np.ndarray:
    """The next stop by the separate walk, checked against sorting every crossing."""
    box_tmax = tmax.astype(np.float64) * (1.0 + BOX_TMAX_SLACK_REL)
    want = nearest_by_crossings(world, remote, origin, direction, box_tmax, visited)
    np.testing.assert_array_equal(
        nearest_unvisited(world, remote, origin, direction, tmax, visited), want)
    return want


def _doubled(scene):
    """Every instance twice, coincident: boxes entered at equal t on different shards."""
    inst = scene.instances
    return dataclasses.replace(scene, instances=Instances(
        np.concatenate([inst.mesh, inst.mesh]), np.concatenate([inst.transform] * 2)))


# (FLAT_WALK_MAX, ROUTE_FLAT_MAX): the local walk and the routing search, each through its
# flat loop or the BVH; mixed is a shard's usual case (few local boxes, many candidates).
WALKS = {"flat": (10**6, 10**6), "bvh": (0, 0), "mixed": (10**6, 0)}


@pytest.mark.parametrize("walk", list(WALKS))
@pytest.mark.parametrize("name,size,k", [("forest", "small", 3), ("city", "small", 5),
                                         ("forest", "default", 8), ("sculpture", "tiny", 2),
                                         ("forest", "doubled", 4)])
def test_fused_walk_routes_like_a_second_walk(name, size, k, walk, monkeypatch):
    monkeypatch.setattr(toplevel, "FLAT_WALK_MAX", WALKS[walk][0])
    monkeypatch.setattr(toplevel, "ROUTE_FLAT_MAX", WALKS[walk][1])
    rng = np.random.default_rng(zlib.crc32(f"{name}{size}{k}".encode()))
    scene = _doubled(make_demo(name, "tiny")) if size == "doubled" else make_demo(name, size)
    m = len(scene.instance_mesh)
    splits = [rng.integers(0, k, m),  # scattered
              np.argsort(np.argsort(np.asarray(  # spatially coherent, by x
                  [np.mean(b[:, 0]) for b in ShardWorld.build(scene, np.zeros(m, np.int32))
                   .table.world_bounds]))) * k // m]
    routed = 0
    for owner in splits:
        world = ShardWorld.build(scene, owner)
        for shard in range(k):
            local_inst = world.local_instances(shard)
            remote = np.flatnonzero(world.owner != shard).astype(np.int32)
            held = set(np.asarray(scene.instance_mesh)[local_inst].tolist())
            geo = LocalGeometry({i: MeshGeometry(scene.meshes[i]) for i in held}, world.table,
                                local_inst)
            cand = candidate_owner(world, remote)
            n = 3000
            o1, d1 = _aimed(world, scene, rng, n)
            o2, d2 = _random(world, rng, n)
            origin, direction = np.concatenate([o1, o2]), np.concatenate([d1, d2])
            n = len(origin)
            span = float(np.ptp(world.table.world_bounds))
            tmax = np.where(rng.random(n) < 0.5, np.inf,
                            rng.uniform(0, span, n)).astype(np.float32)
            visited = (rng.integers(0, 1 << k, n).astype(np.uint64)
                       | (np.uint64(1) << np.uint64(shard)))
            visited[::5] = np.uint64(1) << np.uint64(shard)  # fresh rays

            record = np.full(n, NO_HIT, np.int32)
            want = geo.intersect_closest(origin, direction, tmax, record, record)
            *got, near = geo.closest_routed(origin, direction, tmax, record, record, cand,
                                            visited)
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
            # The final tmax is at most the walk's cut (hits only shorten a ray).
            assert (got[0] <= near.walk_tmax).all()
            for final in (got[0], _cuts(world, remote, origin, direction, near.walk_tmax, rng)):
                expect = _second_walk(world, remote, origin, direction, final, visited)
                np.testing.assert_array_equal(next_stop(near, final), expect)
                routed += int((expect != DONE).sum())

            # Shadow rays keep their tmax: random, and on the edge of a box entry.
            for t_sh in (tmax, _cuts(world, remote, origin, direction, tmax, rng)):
                occluded, near = geo.occluded_routed(origin, direction, t_sh, cand, visited)
                np.testing.assert_array_equal(
                    occluded, geo.intersect_occluded(origin, direction, t_sh))
                free = ~occluded
                expect = _second_walk(world, remote, origin[free], direction[free],
                                      t_sh[free], visited[free])
                np.testing.assert_array_equal(next_stop(near.take(free), t_sh[free]), expect)
                routed += int((expect != DONE).sum())
    assert routed > 1000, f"only {routed} rays had a next stop: the test checks too little"
