"""The routing kernel (one candidate per ray, BVH nodes culled beyond it) picks exactly the
shard that listing every crossing and sorting picks: nearest box entry before tmax among
unvisited shards, ties to the lowest owner."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.demos import make_demo
from nprt.workers.routing.exact import DONE, nearest_unvisited
from nprt.workers.traversal import toplevel
from nprt.workers.traversal.local import BOX_TMAX_SLACK_REL
from nprt.workers.wavefront.world import ShardWorld
from tests.workers.oracles import nearest_by_crossings

K = 5


def _rays(world, n: int, rng) -> tuple:
    lo, hi = world.table.world_bounds[:, 0].min(0), world.table.world_bounds[:, 1].max(0)
    origin = rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (n, 3))
    direction = rng.normal(size=(n, 3)).astype(np.float32)
    direction[::7, rng.integers(0, 3)] = 0.0  # zero components go through the slab test
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    tmax = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0, np.abs(hi - lo).max(), n))
    visited = rng.integers(0, 1 << K, n).astype(np.uint64)
    return origin, direction, tmax.astype(np.float32), visited


@pytest.mark.parametrize("search", ["flat", "bvh"])
@pytest.mark.parametrize("name", ["forest", "city"])
def test_kernel_routes_like_sorting_every_crossing(name, search, monkeypatch):
    # every candidate's slab in one loop, or the BVH walk culled at the best so far
    monkeypatch.setattr(toplevel, "ROUTE_FLAT_MAX", 10**6 if search == "flat" else 0)
    rng = np.random.default_rng(3)
    scene = make_demo(name, "small")
    world = ShardWorld.build(scene, rng.integers(0, K, len(scene.instance_mesh)))
    remote = np.flatnonzero(world.owner != 0).astype(np.int32)
    assert world.table.bvh_inputs is not None
    origin, direction, tmax, visited = _rays(world, 20_000, rng)
    got = nearest_unvisited(world, remote, origin, direction, tmax, visited)
    box_tmax = tmax.astype(np.float64) * (1.0 + BOX_TMAX_SLACK_REL)
    want = nearest_by_crossings(world, remote, origin, direction, box_tmax, visited)
    assert (want != DONE).sum() > 1000, "too few rays cross an unvisited box to test"
    np.testing.assert_array_equal(got, want)

