"""The top-level slab test (`InstanceTable.box_entries`, BVH and plain-loop kernels)
against a plain numpy oracle: same crossings, order, dtypes and t values; the compiled
BVH builder on awkward boxes, and the BVH shipped (not rebuilt) with a pickled table."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import trimesh

from nprt.workers.kernels import bvh as kernels
from nprt.workers.traversal.toplevel import BVH_MIN_INSTANCES, InstanceTable
from tests.workers import oracles
from tests.workers.helpers import Instance, Scene, mesh_from_trimesh, plane_mesh, trs


def _oracle(boxes, origin, direction, tmax, instances):
    """Every ray against every requested box on (n, k) arrays, in one piece.

    boxes : (m, 2, 3) float64; origin, direction : (n, 3); tmax : (n,); instances : (k,)
    returns ray (p,) int64, inst (p,) int32, t_enter, t_exit (p,) float64
    """
    b = boxes[np.asarray(instances, np.int64)]  # (k, 2, 3)
    o = np.asarray(origin, np.float64)[:, None, :]  # (n, 1, 3)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = (1.0 / np.asarray(direction, np.float64))[:, None, :]
        t0 = (b[None, :, 0, :] - o) * inv  # (n, k, 3)
        t1 = (b[None, :, 1, :] - o) * inv
        lo, hi = np.fmin(t0, t1), np.fmax(t0, t1)
        t_enter = np.fmax(np.fmax(lo[..., 0], lo[..., 1]), lo[..., 2])  # (n, k)
        t_exit = np.fmin(np.fmin(hi[..., 0], hi[..., 1]), hi[..., 2])
        tm = np.asarray(tmax, np.float64)[:, None]
        ok = (t_exit >= np.maximum(t_enter, 0.0)) & (t_enter < tm)
    ray, col = np.nonzero(ok)
    return (ray.astype(np.int64), np.asarray(instances)[col].astype(np.int32),
            t_enter[ray, col], t_exit[ray, col])


def _assert_same(got, want, what=""):
    names = ("ray", "inst", "t_enter", "t_exit")
    for name, g, w in zip(names, got, want, strict=True):
        assert g.dtype == w.dtype, f"{what} {name}: dtype {g.dtype}, want {w.dtype}"
        assert g.shape == w.shape, f"{what} {name}: {g.shape} crossings, want {w.shape}"
        if g.dtype.kind == "f":
            # Bit-identical, up to the sign of a zero: numpy's own fmin/fmax give -0.0 or
            # 0.0 on a zero tie depending on the array length (SIMD or scalar loop).
            g, w = g + 0.0, w + 0.0
            bad = np.flatnonzero(g.view(np.int64) != w.view(np.int64))
        else:
            bad = np.flatnonzero(g != w)
        assert len(bad) == 0, (f"{what} {name}: {len(bad)} rows differ, first at {bad[0]}: "
                               f"got {g[bad[:3]]}, want {w[bad[:3]]}")


def _rays(rng, boxes, n, span):
    """Awkward rays for these boxes: random, inside boxes, on slab planes, with zero
    (and -0.0) direction components, a few all-zero or non-finite; tmax cuts."""
    o = rng.uniform(-span, span, size=(n, 3))
    pick = rng.integers(0, len(boxes), n)
    inside = rng.random(n) < 0.3
    o[inside] = boxes[pick[inside]].mean(axis=1)
    on_plane = rng.random((n, 3)) < 0.2  # a coordinate exactly on a lo or hi plane
    side = rng.integers(0, 2, size=(n, 3))
    planes = boxes[pick[:, None], side, np.arange(3)[None, :]]  # (n, 3)
    o = np.where(on_plane, planes, o).astype(np.float32)
    d = rng.normal(size=(n, 3))
    d = np.where(rng.random((n, 3)) < 0.35, 0.0, d)
    d = np.where(rng.random((n, 3)) < 0.5, d, -d)  # -0.0 components too
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    d[:: 97] = 0.0  # no direction at all
    d = d.astype(np.float32)
    tmax = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(-1.0, 2 * span, n))
    tmax[:: 89] = 0.0
    tmax = tmax.astype(np.float32)
    o[5], d[6], tmax[7] = (np.nan, 0, 0), (np.inf, 0, 0), np.nan  # take the plain loop
    return o, d, tmax


def _random_scene(rng, m):
    cube = mesh_from_trimesh(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), "cube")
    flat = plane_mesh(half=1.0)  # zero thickness: only the padding gives it a slab
    sliver = mesh_from_trimesh(trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0.5, 0, 1e-7]],
                                               [[0, 1, 2]], process=False), "sliver")
    inst = [Instance(1, trs((0, 0, 0), 30.0))]  # a ground covering everything
    for _ in range(m - 1):
        mesh = int(rng.integers(0, 3))
        axis_aligned = rng.random() < 0.5
        inst.append(Instance(mesh, trs(rng.uniform(-8, 8, 3), rng.uniform(0.05, 3.0),
                                       rng.normal(size=3),
                                       0.0 if axis_aligned else rng.uniform(0, 360))))
    return Scene((cube, flat, sliver), tuple(inst))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_box_entries_equals_numpy_oracle_on_awkward_rays(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    table = InstanceTable(_random_scene(rng, 60))
    o, d, tmax = _rays(rng, table.world_bounds, 3000, 10.0)
    used = []
    for name in ("bvh_slab", "slab_all"):
        fn = getattr(kernels, name)
        monkeypatch.setattr(kernels, name,
                            lambda *a, _fn=fn, _name=name: used.append(_name) or _fn(*a))
    m = len(table)
    subsets = {
        "all": np.arange(m),
        "all, int32, reversed": np.arange(m)[::-1].astype(np.int32),
        "random half, shuffled": rng.permutation(m)[: m // 2],
        "few": rng.permutation(m)[:BVH_MIN_INSTANCES],
        "one": np.array([int(rng.integers(0, m))]),
        "repeated": np.r_[np.arange(20), np.arange(5, 15)],
        "negative": np.array([-1, -m, 3] + list(range(10, 20))),
    }
    crossings = 0
    for what, instances in subsets.items():
        used.clear()
        got = table.box_entries(o, d, tmax, instances)
        _assert_same(got, _oracle(table.world_bounds, o, d, tmax, instances), what)
        crossings += len(got[0])
        if what.startswith(("all", "random")):
            assert used == ["bvh_slab"], f"{what}: ran {used}, expected the BVH"
    assert crossings > 2 * len(o), f"only {crossings} crossings: the rays test too little"


def test_box_entries_on_empty_inputs():
    table = InstanceTable(_random_scene(np.random.default_rng(4), 12))
    o, d = np.zeros((3, 3), np.float32), np.ones((3, 3), np.float32)
    tmax = np.full(3, np.inf, np.float32)
    empty = np.zeros(0, np.int64)
    z3 = np.zeros((0, 3), np.float32)
    for args in ((o, d, tmax, empty), (z3, z3, np.zeros(0, np.float32), np.arange(12))):
        _assert_same(table.box_entries(*args), _oracle(table.world_bounds, *args))


def test_box_entries_takes_float64_and_read_only_rays():
    rng = np.random.default_rng(5)
    table = InstanceTable(_random_scene(rng, 30))
    o, d, tmax = _rays(rng, table.world_bounds, 500, 10.0)
    o64, d64 = o.astype(np.float64) + 1e-9, d.astype(np.float64)
    for a in (o64, d64, tmax):
        a.flags.writeable = False
    want = _oracle(table.world_bounds, o64, d64, tmax, np.arange(30))
    _assert_same(table.box_entries(o64, d64, tmax, np.arange(30)), want)


def test_unpickled_table_gives_the_same_crossings():
    rng = np.random.default_rng(6)
    table = InstanceTable(_random_scene(rng, 40))
    o, d, tmax = _rays(rng, table.world_bounds, 1000, 10.0)
    copy = pickle.loads(pickle.dumps(table))
    copy.world_bounds.flags.writeable = False  # as read back from Ray's object store
    _assert_same(copy.box_entries(o, d, tmax, np.arange(40)),
                 table.box_entries(o, d, tmax, np.arange(40)))


def _raw_boxes(rng, m):
    """Boxes on a coarse float32 grid, many exactly flat in one to three axes (no
    padding), so float32 origins can sit exactly on their planes."""
    lo = np.round(rng.uniform(-6, 6, size=(m, 3)) * 4) / 4
    ext = np.round(rng.uniform(0, 4, size=(m, 3)) * 4) / 4
    ext[rng.random((m, 3)) < 0.3] = 0.0
    return np.stack([lo, lo + ext], axis=1)  # (m, 2, 3) float64


@pytest.mark.parametrize("seed", [10, 11])
def test_bvh_kernel_equals_oracle_on_unpadded_flat_boxes(seed):
    # Flat boxes make the reference formula's NaN cases (origin on a plane, zero
    # direction) matter: the BVH's inner-node test must still never cull a crossing.
    rng = np.random.default_rng(seed)
    boxes = _raw_boxes(rng, 80)
    o, d, tmax = _rays(rng, boxes, 4000, 8.0)
    o = np.where(rng.random(o.shape) < 0.3, np.round(o * 4) / 4, o).astype(np.float32)
    bvh = kernels.bvh_build(boxes)
    node_box, node_child = bvh[0], bvh[1]
    inner = np.flatnonzero(node_child >= 0)
    for c in (node_child[inner], node_child[inner] + 1):  # parents hold their children
        assert (node_box[inner, 0] <= node_box[c, 0]).all()
        assert (node_box[inner, 1] >= node_box[c, 1]).all()
    for instances in (np.arange(80), rng.permutation(80)[:50]):
        col_of = np.full(80, -1, np.int32)
        col_of[instances] = np.arange(len(instances), dtype=np.int32)
        ray, col, t_enter, t_exit = kernels.bvh_slab(
            o.astype(np.float64), d.astype(np.float64), tmax.astype(np.float64), boxes,
            *bvh, col_of)
        got = (ray, instances[col].astype(np.int32), t_enter, t_exit)
        _assert_same(got, _oracle(boxes, o, d, tmax, instances))
        ray, col, t_enter, t_exit = kernels.slab_all(
            o.astype(np.float64), d.astype(np.float64), tmax.astype(np.float64),
            np.ascontiguousarray(boxes[instances]))
        got = (ray, instances[col].astype(np.int32), t_enter, t_exit)
        _assert_same(got, _oracle(boxes, o, d, tmax, instances))


def _awkward_boxes(kind: str, rng) -> np.ndarray:
    """(m, 2, 3) float64 boxes that stress the binned builder."""
    if kind == "one":
        return _raw_boxes(rng, 1)
    if kind == "three":
        return _raw_boxes(rng, 3)
    if kind == "identical":  # every centroid equal: no bin split exists anywhere
        return np.repeat(_raw_boxes(rng, 1), 40, axis=0)
    if kind == "points":  # zero-volume boxes, several exact duplicates
        p = np.round(rng.uniform(-4, 4, (60, 3)) * 2) / 2
        p[::3] = p[0]
        return np.stack([p, p], axis=1)
    if kind == "line":  # centroids spread along x only, and clustered
        lo = np.zeros((70, 3))
        lo[:, 0] = np.repeat(rng.uniform(-5, 5, 7), 10)
        return np.stack([lo, lo + 0.5], axis=1)
    if kind == "nested":  # one huge box around many tiny ones, and far outliers
        b = _raw_boxes(rng, 50) * 1e-3
        b[0] = [[-1e6, -1e6, -1e6], [1e6, 1e6, 1e6]]
        b[1] = [[1e300, 0, 0], [1.5e300, 1, 1]]
        b[2] = [[-1.7e308, -1.7e308, 0], [-1e308, -1e308, 1]]
        return b
    return _raw_boxes(rng, 200)


def _check_tree(boxes, bvh):
    """The structure `_bvh_fill` relies on: children hold what is below them, leaves of
    1..BVH_LEAF_SIZE prims tile prim, which lists every box once."""
    node_box, node_child, node_start, node_count, prim = bvh
    m = len(boxes)
    assert prim.dtype == np.int32 and np.array_equal(np.sort(prim), np.arange(m))
    leaf = node_child < 0
    assert len(node_child) == 2 * leaf.sum() - 1 and node_child.dtype == np.int32  # binary
    assert ((node_count[leaf] >= 1) & (node_count[leaf] <= kernels.BVH_LEAF_SIZE)).all()
    order = np.argsort(node_start[leaf])
    starts, counts = node_start[leaf][order], node_count[leaf][order]
    assert starts[0] == 0 and np.array_equal(starts[1:], np.cumsum(counts)[:-1])
    assert counts.sum() == m
    inner = np.flatnonzero(~leaf)
    assert (node_child[inner] > inner).all() and (node_child[inner] + 1 < len(node_child)).all()
    for c in (node_child[inner], node_child[inner] + 1):
        assert (node_box[inner, 0] <= node_box[c, 0]).all()
        assert (node_box[inner, 1] >= node_box[c, 1]).all()
        assert (node_count[inner] >= node_count[c]).all()
    for node in np.flatnonzero(leaf):
        b = boxes[prim[node_start[node]:node_start[node] + node_count[node]]]
        assert (node_box[node, 0] < b[:, 0]).all() and (node_box[node, 1] > b[:, 1]).all()


@pytest.mark.parametrize("kind", ["one", "three", "identical", "points", "line", "nested",
                                  "random"])
def test_compiled_bvh_builder_equals_brute_force(kind):
    """The binned-SAH builder on degenerate and flat boxes: a valid tree, and traversal
    through it finds exactly the brute-force crossings."""
    rng = np.random.default_rng(len(kind))
    boxes = _awkward_boxes(kind, rng)
    bvh = kernels.bvh_build(boxes)
    _check_tree(boxes, bvh)
    finite = np.isfinite(boxes).all() and np.abs(boxes).max() < 1e10
    o, d, tmax = _rays(rng, boxes if finite else boxes[3:], 3000, 8.0)
    m = len(boxes)
    for instances in (np.arange(m), rng.permutation(m)[: max(1, m // 2)]):
        col_of = np.full(m, -1, np.int32)
        col_of[instances] = np.arange(len(instances), dtype=np.int32)
        ray, col, t_enter, t_exit = kernels.bvh_slab(
            o.astype(np.float64), d.astype(np.float64), tmax.astype(np.float64), boxes,
            *bvh, col_of)
        got = (ray, instances[col].astype(np.int32), t_enter, t_exit)
        _assert_same(got, _oracle(boxes, o, d, tmax, instances), kind)


def test_bvh_builder_refuses_bad_shapes():
    for bad in (np.zeros((0, 2, 3)), np.zeros((4, 3, 3)), np.zeros((2, 3))):
        with pytest.raises(ValueError, match="shape"):
            kernels.bvh_build(bad)


def test_unpickling_a_table_ships_its_bvh_and_never_rebuilds_it(monkeypatch):
    rng = np.random.default_rng(12)
    table = InstanceTable(_random_scene(rng, 60))
    o, d, tmax = _rays(rng, table.world_bounds, 1000, 10.0)
    want = table.box_entries(o, d, tmax, np.arange(60))
    blob = pickle.dumps(table)

    def no_build(boxes):
        raise AssertionError("bvh_build called while unpickling")

    monkeypatch.setattr(kernels, "bvh_build", no_build)
    copy = pickle.loads(blob)
    for a, b in zip(copy.bvh, table.bvh, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert all(a.flags.writeable and a.flags.c_contiguous for a in copy.bvh)
    _assert_same(copy.box_entries(o, d, tmax, np.arange(60)), want)


def test_single_instance_table_uses_its_bvh():
    table = InstanceTable(Scene((plane_mesh(half=1.0),), (Instance(0, trs((1, 2, 3))),)))
    assert len(table.bvh[1]) == 1 and table.bvh[1][0] == -1  # one leaf
    rng = np.random.default_rng(13)
    o, d, tmax = _rays(rng, table.world_bounds, 500, 4.0)
    col_of = np.zeros(1, np.int32)
    got = kernels.bvh_slab(o.astype(np.float64), d.astype(np.float64),
                           tmax.astype(np.float64), table.world_bounds, *table.bvh, col_of)
    want = _oracle(table.world_bounds, o, d, tmax, np.arange(1))
    _assert_same((got[0], got[1], got[2], got[3]), want)


def test_to_local_sums_in_a_fixed_order():
    # The exact float32 answer of the fixed float64 order, and the plain einsum up to
    # rounding (einsum's own order is numpy's choice; it was this one on numpy 2.4).
    rng = np.random.default_rng(9)
    table = InstanceTable(_random_scene(rng, 40))
    n = 5000
    inst = rng.integers(0, len(table), n).astype(np.int32)
    o = rng.uniform(-10, 10, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    lo, ld = oracles.to_local(table, inst, o, d)
    m = table.world_to_local[inst]  # (n, 3, 4) float64
    o64, d64 = o.astype(np.float64)[:, None, :], d.astype(np.float64)[:, None, :]
    p_o, p_d = m[:, :, :3] * o64, m[:, :, :3] * d64  # (n, 3, 3) products
    want_o = (((p_o[..., 0] + p_o[..., 2]) + p_o[..., 1]) + m[:, :, 3]).astype(np.float32)
    want_d = ((p_d[..., 0] + p_d[..., 2]) + p_d[..., 1]).astype(np.float32)
    assert np.array_equal(lo, want_o) and np.array_equal(ld, want_d)
    e_o = np.einsum("nij,nj->ni", m[:, :, :3], o64[:, 0]) + m[:, :, 3]
    scale = np.abs(p_o).sum(axis=2) + np.abs(m[:, :, 3])  # cancellation bound
    assert (np.abs(lo - e_o) <= 1e-6 * scale).all()
    assert np.allclose(ld, np.einsum("nij,nj->ni", m[:, :, :3], d64[:, 0]), rtol=1e-6,
                       atol=1e-6)
