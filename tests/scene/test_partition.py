"""Partitioning: coverage, the byte bound, splitting of instances, errors, determinism (the
work balance: test_partition_work.py)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from nprt.scene.demos import make_demo
from nprt.scene.errors import SceneError
from nprt.scene.model import Instance, Mesh, Scene, instance_world_bounds
from nprt.scene.partition import BYTE_SLACK, partition
from tests.scene._util import translate


def _strip(n_faces: int, name: str) -> Mesh:
    """A triangle strip with n_faces faces (nbytes grows with n_faces)."""
    x = np.arange(n_faces + 2, dtype=np.float32)
    v = np.column_stack([x, np.arange(n_faces + 2) % 2, np.zeros_like(x)]).astype(np.float32)
    i = np.arange(n_faces)
    return Mesh(name, v, np.stack([i, i + 1, i + 2], 1).astype(np.uint32))


def _scene(face_counts: list[int], per_mesh: int = 1) -> Scene:
    meshes = tuple(_strip(n, f"m{j}") for j, n in enumerate(face_counts))
    inst = tuple(Instance(j, translate(10.0 * j, 0.0, 5.0 * r))
                 for j in range(len(meshes)) for r in range(per_mesh))
    return Scene(meshes, inst)


def _check_consistent(scene: Scene, p) -> None:
    n = len(scene.instances)
    assert p.instance_shard.shape == (n,) and p.instance_shard.dtype == np.int32
    assert p.shard_bytes.shape == (p.k,) and p.shard_bytes.dtype == np.int64
    owned = np.concatenate([p.shard_instances(s) for s in range(p.k)])
    assert np.array_equal(np.sort(owned), np.arange(n)), "each instance exactly once"
    mesh_of = np.array([i.mesh for i in scene.instances])
    for s in range(p.k):
        idx = p.shard_instances(s)
        assert len(idx) >= 1, f"shard {s} is empty"
        assert p.shard_meshes[s] == tuple(sorted(set(mesh_of[idx].tolist())))
        assert p.shard_bytes[s] == sum(scene.meshes[m].nbytes for m in p.shard_meshes[s])
    assert p.max_shard_bytes == int(p.shard_bytes.max())


@pytest.mark.parametrize("k", [1, 2, 3, 5, 8, 13, 39])
def test_partition_covers_every_instance_exactly_once(k):
    scene = make_demo("forest", "small")
    _check_consistent(scene, partition(scene, k))


def test_single_shard_holds_everything():
    scene = make_demo("city", "tiny")
    p = partition(scene, 1)
    assert p.max_shard_bytes == scene.mesh_bytes
    assert p.shard_meshes == (tuple(range(len(scene.meshes))),)


def _optimum(nbytes: list[int], k: int) -> int:
    best = None
    for assign in itertools.product(range(k), repeat=len(nbytes)):
        if len(set(assign)) < k:
            continue
        loads = np.bincount(assign, weights=nbytes, minlength=k)
        best = loads.max() if best is None else min(best, loads.max())
    return int(best)


@pytest.mark.parametrize("seed", range(6))
def test_partition_balances_bytes_within_the_greedy_bound(seed):
    rng = np.random.default_rng(seed)
    scene = _scene(rng.integers(1, 400, size=7).tolist())
    nbytes = [m.nbytes for m in scene.meshes]
    for k in (2, 3):
        p = partition(scene, k)
        _check_consistent(scene, p)
        # The bytes-only rule (largest first), which sets the cap, is within 4/3 of the best
        # possible makespan; the work-balanced placement stays under the cap it sets.
        assert p.bytes_only_max <= 4 / 3 * _optimum(nbytes, k)
        assert p.max_shard_bytes <= p.byte_cap == max(int(BYTE_SLACK * p.bytes_only_max),
                                                      max(nbytes))


def test_partition_puts_the_largest_meshes_on_different_shards():
    scene = _scene([1000, 900, 10, 10, 10, 10])
    p = partition(scene, 2)
    assert p.shard_meshes[0] != p.shard_meshes[1]
    assert {0, 1} not in [set(ms) for ms in p.shard_meshes]
    assert any(0 in ms for ms in p.shard_meshes) and any(1 in ms for ms in p.shard_meshes)


def test_more_shards_than_meshes_splits_instances_and_replicates_the_mesh():
    scene = _scene([50, 20], per_mesh=6)
    p = partition(scene, 5)
    _check_consistent(scene, p)
    assert p.summary()["split_meshes"] == [0, 1]
    assert sum(len(p.mesh_shards(m)) for m in range(2)) == 5
    # Each shard holds exactly one piece, so no shard holds more than the largest mesh.
    assert p.max_shard_bytes == max(m.nbytes for m in scene.meshes)


def test_split_instances_are_spatially_coherent():
    rng = np.random.default_rng(1)
    grid = [(x, z) for x in range(8) for z in range(8)]
    order = rng.permutation(len(grid))
    inst = tuple(Instance(0, translate(10.0 * grid[i][0], 0.0, 10.0 * grid[i][1]))
                 for i in order)
    scene = Scene((_strip(5, "rock"),), inst)
    # Equal work per rock: the pieces are cut by work, so equal work gives equal counts.
    p = partition(scene, 4, work=np.ones(len(inst)))
    centres = instance_world_bounds(scene).mean(axis=1)
    boxes = []
    for s in range(4):
        c = centres[p.shard_instances(s)]
        assert len(c) == 16
        boxes.append((c.min(0), c.max(0)))
        # Quadrants of the 8x8 grid: each spans 4 cells (30 m) in x and in z.
        assert np.ptp(c[:, 0]) <= 30.0 + 1e-9 and np.ptp(c[:, 2]) <= 30.0 + 1e-9
    for (alo, ahi), (blo, bhi) in itertools.combinations(boxes, 2):
        overlap = np.minimum(ahi, bhi) - np.maximum(alo, blo)
        assert (overlap[[0, 2]] < 0).any(), "two shards' instance regions interleave"


def test_partition_is_deterministic():
    scene = make_demo("sculpture", "small")
    a, b = partition(scene, 9), partition(scene, 9)
    assert np.array_equal(a.instance_shard, b.instance_shard)
    assert a.shard_meshes == b.shard_meshes and np.array_equal(a.shard_bytes, b.shard_bytes)


@pytest.mark.parametrize("k", [0, -2, 2.5, True])
def test_partition_rejects_bad_shard_counts(k):
    with pytest.raises(SceneError, match="shard count must be an integer >= 1"):
        partition(make_demo("forest", "tiny"), k)


def test_partition_rejects_more_shards_than_instances():
    scene = make_demo("forest", "tiny")
    n = len(scene.instances)
    with pytest.raises(SceneError, match=rf"only {n} instances \(use k <= {n}\)"):
        partition(scene, n + 1)
    _check_consistent(scene, partition(scene, n))


def test_summary_reports_balance_and_counts():
    scene = make_demo("city", "tiny")
    s = partition(scene, 4).summary()
    assert s["k"] == 4 and len(s["shard_bytes"]) == 4
    assert sum(s["instances_per_shard"]) == len(scene.instances)
    assert s["max_shard_bytes"] == max(s["shard_bytes"]) and s["imbalance"] >= 1.0


def test_replicated_meshes_take_no_piece_and_every_shard_holds_them():
    scene = make_demo("forest", "small")  # mesh 0 is the ground: one instance
    p = partition(scene, 4, replicated=[0])
    assert all(0 in ms for ms in p.shard_meshes)
    mesh_of = np.asarray(scene.instance_mesh)
    # every shard owns instances of some other mesh: the ground did not take a shard
    for s in range(4):
        assert (mesh_of[p.shard_instances(s)] != 0).any()
    assert np.array_equal(p.shard_bytes, [sum(scene.meshes[m].nbytes for m in ms)
                                          for ms in p.shard_meshes])
