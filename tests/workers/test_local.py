"""Two-level intersection (LocalGeometry): many instances of one base mesh along a ray."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.model import Instance, Mesh, Scene
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.traversal.toplevel import InstanceTable
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


def test_closest_hit_in_rounds_equals_one_round_over_every_crossing(monkeypatch):
    # Rounds take each ray's nearest boxes first and cull boxes entered beyond the closest
    # hit so far; one round over every crossing culls nothing: the answers must be equal
    # bit for bit, ties included.
    import nprt.workers.traversal.local as local

    geo, o, d, tmax = _rays_through_overlapping_trees(20000, 3)
    rounds = geo.intersect_closest(o, d, tmax)
    monkeypatch.setattr(local, "ROUNDS", (0,))
    once = geo.intersect_closest(o, d, tmax)
    assert (rounds[1] >= 0).mean() > 0.2, "too few hits to compare"
    for name, a, b in zip(("t", "inst", "prim", "u", "v"), rounds, once, strict=True):
        assert np.array_equal(a, b), f"{name} differs in {(a != b).sum()} rays"


def test_occlusion_in_rounds_equals_one_round_over_every_crossing(monkeypatch):
    import nprt.workers.traversal.local as local

    geo, o, d, tmax = _rays_through_overlapping_trees(20000, 4)
    rounds = geo.intersect_occluded(o, d, tmax)
    monkeypatch.setattr(local, "ROUNDS", (0,))
    assert np.array_equal(rounds, geo.intersect_occluded(o, d, tmax))


def test_entry_rank_orders_each_rays_crossings_by_entry_then_position():
    from nprt.workers.kernels.pairs import entry_rank

    rng = np.random.default_rng(5)
    ray = np.sort(rng.integers(0, 300, 3000)).astype(np.int64)
    t = rng.choice([0.0, 0.5, 1.0, 2.5, np.inf], len(ray))  # many ties
    rank = entry_rank(ray, t)
    order = np.lexsort((np.arange(len(ray)), t, ray))  # by ray, then t, then position
    want = np.empty(len(ray), np.int64)
    first = np.searchsorted(ray[order], ray[order])  # start of each ray's run
    want[order] = np.arange(len(ray)) - first
    assert np.array_equal(rank, want)
