"""The compiled proxy-query kernels (nprt.workers.routing.proxy_pairs) give the bits of the
numpy formulas they replaced (tests/workers/proxy_oracles.py): the pair geometry on awkward
transforms and rays, the decision rules with ties everywhere, and predict as a whole on a
demo scene with its shipped proxies."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from nprt.scene.model import Camera, Instance, Scene
from nprt.scene.store import open_scene
from nprt.workers.routing import proxy_pairs, proxy_query
from nprt.workers.routing.proxy_query import Query, QueryKnobs, predict, predict_together
from nprt.workers.settings import ProxySettings, RenderSettings
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.inprocess import shards_in_process
from tests.workers import proxy_oracles as oracle
from tests.workers.helpers import mesh_from_trimesh, trs


def _same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(p,) bool per row: the same bits, or NaN on both sides."""
    a, b = a.reshape(len(a), -1), b.reshape(len(b), -1)
    eq = (a == b) & (np.signbit(a) == np.signbit(b)) if a.dtype.kind == "f" else a == b
    if a.dtype.kind == "f":
        eq |= np.isnan(a) & np.isnan(b)
    return eq.all(axis=1)


def _table(rng) -> InstanceTable:
    """Boxes at scales 1e-3..1e3, rotated, up to 1e6 from the origin, one axis-aligned."""
    meshes = (mesh_from_trimesh(trimesh.creation.box((1.0, 2.0, 0.5)), "a"),
              mesh_from_trimesh(trimesh.creation.icosphere(1), "b"))
    inst = [Instance(0, np.eye(4))]
    for k in range(40):
        axis = rng.normal(size=3)
        scale = 10.0 ** rng.uniform(-3, 3)
        pos = rng.uniform(-5, 5, 3) * (1.0 if k % 3 else 10.0 ** rng.uniform(0, 5))
        inst.append(Instance(k % 2, trs(pos, scale, axis, rng.uniform(0, 360))))
    return InstanceTable(Scene(meshes, tuple(inst), camera=Camera(
        eye=(0, 0, -5), target=(0, 0, 0), up=(0, 1, 0), fov_deg=40)))


def _rays(rng, table: InstanceTable, n: int):
    """(n, 3) float64 origins near the boxes (some inside, some on a box plane), (n, 3) float32
    directions with zero and -0.0 components and all-zero rays, (n,) float32 tmax."""
    lo, hi = table.world_bounds[:, 0], table.world_bounds[:, 1]
    pick = rng.integers(0, len(lo), n)
    c, r = 0.5 * (lo[pick] + hi[pick]), 0.5 * (hi[pick] - lo[pick])
    origin = c + r * rng.uniform(-2, 2, (n, 3))
    origin[::9, 1] = 0.0  # instance 0's box planes are at y = +-1
    origin[::9, 0] = rng.uniform(-0.5, 0.5, len(origin[::9]))
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    d[::5, 0] = 0.0
    d[::7, 2] = -0.0
    d[::31] = 0.0
    tmax = np.where(rng.random(n) < 0.3, np.inf, rng.uniform(0.5, 50, n) * r.max(1))
    return origin, d, tmax.astype(np.float32)


@pytest.mark.parametrize("seed", range(4))
def test_box_queries_give_the_numpy_bits(seed):
    rng = np.random.default_rng(seed)
    table = _table(rng)
    origin, direction, tmax = _rays(rng, table, 3000)
    ray = rng.integers(0, len(origin), 20000).astype(np.int64)
    inst = rng.integers(0, len(table), len(ray)).astype(np.int32)
    q = oracle.box_queries(table, inst, origin[ray], direction[ray], tmax[ray])
    got = proxy_pairs.box_queries(ray, inst, origin, direction.astype(np.float64), tmax,
                                  table.kernel_arrays()[2], table.local_bounds)
    assert q.crosses.any() and q.internal.any() and (q.crosses & ~q.internal).any()
    for name, want, have in zip(("crosses", "internal", "t_box", "length", "point", "qdir"),
                                (q.crosses, q.internal, q.t_box, q.length, q.point, q.qdir),
                                got, strict=True):
        assert want.dtype == have.dtype, name
        differ = np.flatnonzero(~_same(want, have))
        assert not len(differ), f"{name} differs at pairs {differ[:5]}"


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("asked", ["bvh", "flat", "repeated"])
def test_walk_queries_keep_the_crossed_pairs_of_box_entries(seed, asked):
    """walk_queries = box_entries, less visited shards' boxes, then box_queries, kept where
    the local box is crossed: the same pairs in the same order with the same bits, through
    the BVH (more than BVH_MIN_INSTANCES boxes asked) or the plain loop (few, or repeated),
    and through the vectorised flat loop over the same boxes, with and without visited
    masks, directions as float64 or as the float32 the rays carry, rays with NaN and inf
    components included."""
    rng = np.random.default_rng(seed)
    table = _table(rng)
    origin, direction, tmax = _rays(rng, table, 3000)
    origin[::97, 2] = np.nan
    origin[1::97, 0] = np.inf
    remote = {"bvh": np.sort(rng.choice(len(table), 30, replace=False)),
              "flat": np.array([0, 3, 4], np.int64),
              "repeated": np.array([5, 1, 5, 2] + list(range(6, 16)), np.int64)}[asked]
    owner = rng.integers(0, 5, len(table)).astype(np.int32)
    world = _World(table, owner)
    has_m = np.array([True, False])
    boxes, bvh, col_of, members, w2l, bounds, mesh_of = table.pair_inputs(remote)
    assert (len(col_of) > 0) == (asked == "bvh")
    flats = (np.zeros((6, 0)), np.ascontiguousarray(boxes[members].reshape(-1, 6).T))
    for visited, flat, d_type in itertools.product(
            (None, rng.integers(0, 32, len(origin)).astype(np.uint64)), flats,
            (np.float64, np.float32)):
        ray, inst = oracle.asked_boxes(world, remote, origin, direction, tmax, visited)
        q = oracle.box_queries(table, inst, origin[ray], direction[ray], tmax[ray])
        keep = q.crosses
        got = proxy_pairs.walk_queries(
            origin, direction.astype(d_type), tmax, boxes, bvh, col_of, members, flat,
            owner, np.zeros(0, np.uint64) if visited is None else visited,
            visited is not None, w2l, bounds, mesh_of, has_m)
        mesh = table.mesh[inst[keep]].astype(np.int64)
        want = (ray[keep], inst[keep], mesh, has_m[mesh], q.internal[keep], q.t_box[keep],
                q.length[keep], q.point[keep], q.qdir[keep])
        assert keep.sum() > 20 and (~keep).any()
        names = ("ray", "inst", "mesh", "has", "internal", "t_box", "length", "point", "qdir")
        for name, a, b in zip(names, want, got[:9], strict=True):
            assert a.dtype == b.dtype, name
            differ = np.flatnonzero(~_same(a, b))
            assert not len(differ), f"{name} differs at pairs {differ[:5]}"
        grouped, start = got[9:]
        order = np.flatnonzero(want[3])
        order = order[np.argsort(mesh[order], kind="stable")]
        assert grouped.tobytes() == order.astype(np.int64).tobytes()
        assert start.tolist() == [0, *np.cumsum(np.bincount(mesh[want[3]], minlength=2))]


class _World:
    """What asked_boxes reads of a ShardWorld: the table and each instance's owner."""

    def __init__(self, table, owner):
        self.table, self.owner = table, owner


def _pairs(rng, n: int, p: int, meshes: int):
    """Synthetic pairs with ties: t_box on a coarse grid (equal entries and equal predicted
    t), visibilities on the threshold and the band's edges, internal pairs, boxes without a
    proxy, rays with several pairs and known hits tied with proxy hits."""
    ray = np.sort(rng.integers(0, n, p)).astype(np.int64)
    inst = rng.integers(0, 60, p).astype(np.int32)
    mesh = (inst % meshes).astype(np.int64)
    q = oracle.BoxQueries(
        crosses=rng.random(p) < 0.9, internal=rng.random(p) < 0.25,
        t_box=rng.integers(1, 8, p).astype(np.float64) * 0.5,
        point=np.zeros((p, 3), np.float32), qdir=np.zeros((p, 3), np.float32),
        length=rng.choice([0.5, 1.0, 2.0], p),
        tmax=np.where(rng.random(p) < 0.2, 2.5, np.inf).astype(np.float32))
    thr_m = rng.choice([0.4, 0.5], meshes).astype(np.float32)
    band = rng.choice([0.0, 0.1, 0.25], meshes)
    margin_m = rng.choice([0.0, 0.5], meshes)
    has_m = rng.random(meshes) < 0.8
    has = q.crosses & has_m[mesh]
    vis = np.where(has, rng.choice([0.1, 0.4, 0.5, 0.6, 0.75, 0.9, 1.0], p), 0).astype(np.float32)
    tp = np.where(has & (vis >= thr_m[mesh]), rng.integers(0, 4, p) * 0.5, np.inf)
    best_t = np.where(rng.random(n) < 0.3, rng.integers(1, 8, n) * 0.5, np.inf)
    best_i = np.where(np.isfinite(best_t), rng.integers(0, 60, n), -1).astype(np.int32)
    return (ray, inst, mesh, q, has, vis, tp.astype(np.float32), thr_m, band, margin_m,
            best_t.astype(np.float32), best_i)


@pytest.mark.parametrize("seed", range(6))
def test_decide_gives_the_numpy_bits_ties_included(seed):
    rng = np.random.default_rng(seed)
    n = 300
    ray, inst, mesh, q, has, vis, tp, thr_m, band, margin_m, best_t, best_i = _pairs(
        rng, n, 2000, 5)
    t_proxy = np.where(has, tp / q.length, np.inf)
    a = oracle.answer_rules(q, mesh, vis, t_proxy, np.where(has, thr_m[mesh], 0),
                            np.where(has, margin_m[mesh] / q.length, 0.0), has, band)
    want_t, want_i = best_t.copy(), best_i.copy()
    internal, inner_hits = oracle.closest_confident(ray, inst, q, a, want_t, want_i)
    uncertain, first_open = oracle.open_boxes(n, ray, inst, q, a, want_t)
    ambiguous = inner_hits - internal > 0

    got = proxy_pairs.decide(ray, inst, mesh, q.crosses, q.internal, q.t_box, q.length,
                             q.tmax, has, has, vis, tp, thr_m, band, margin_m, best_t, best_i)
    assert a.hit.any() and a.unsure.any() and ambiguous.any() and (first_open >= 0).any()
    assert best_t.tobytes() == want_t.tobytes() and best_i.tobytes() == want_i.tobytes()
    for name, want, have in zip(("internal", "uncertain", "ambiguous", "first_open"),
                                (internal, uncertain, ambiguous, first_open), got, strict=True):
        assert want.dtype == have.dtype and want.tobytes() == have.tobytes(), name


@pytest.fixture(scope="module", params=["forest:small", "city:small"])
def policies(request):
    """Every shard's ProxyPolicy of a small demo at K = 3 (shipped proxies; the tiny demos
    replicate every mesh), at an accuracy target forest's tree proxies meet (at the default
    the plan copies those trees to every shard, and no shard would model anything)."""
    scene = open_scene(request.param).load()
    s = RenderSettings(width=8, height=8, spp=1, shards=3, mode="proxy",
                       proxy=ProxySettings(accuracy_target=0.9))
    return [(sh.world, sh.policy) for sh in shards_in_process(scene, s, warm=False)]


@pytest.mark.parametrize("walk", ["flat", "bvh"])
def test_predict_gives_the_numpy_oracles_answers_on_a_scene(policies, walk, monkeypatch):
    """Field by field, the bits of the numpy formulas, with the remote boxes walked in the
    flat loop (up to FLAT_WALK_MAX, every demo here) and through a BVH over them (above)."""
    monkeypatch.setattr(proxy_query, "FLAT_WALK_MAX", 10**9 if walk == "flat" else 0)
    monkeypatch.setattr(proxy_query, "_WALKS", {})  # the inputs are kept per asked set
    rng = np.random.default_rng(3)
    fields = ("t", "inst", "uncertain", "internal", "ambiguous", "first_open", "asked_ray",
              "asked_mesh")
    asked = 0
    for world, policy in policies:
        flat = proxy_query._walk_inputs(world.table, world.owner, policy.modeled)[4]
        assert (flat.shape[1] > 0) == (walk == "flat")
        origin, direction, tmax = _rays(rng, world.table, 4000)
        visited = rng.integers(0, 8, len(origin)).astype(np.uint64)
        for knobs in (policy.secondary, policy.shadow,
                      QueryKnobs(None, np.full(len(policy.secondary.band), 0.2), 0.5, False)):
            args = (world, policy.proxies, policy.modeled, origin, direction, tmax, knobs,
                    policy.known, visited)
            want, got = oracle.predict_numpy(*args), predict(*args)
            asked += len(want.asked_ray)
            for f in fields:
                a, b = getattr(want, f), getattr(got, f)
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f
    assert asked > 1000


def test_predict_together_gives_each_query_its_own_prediction_in_fewer_net_calls(policies):
    """A step's secondary and shadow rays asked at once (one call of each mesh's nets) get,
    field by field, the bits `predict` gives each kind asked alone: other thresholds, bands
    and margins, odd sizes, and rays with and without visited shards in one call."""
    rng = np.random.default_rng(5)
    fields = ("t", "inst", "uncertain", "internal", "ambiguous", "first_open", "asked_ray",
              "asked_mesh")
    other = QueryKnobs(0.3, np.full(len(policies[0][1].secondary.band), 0.1), 0.5, False)
    fewer = 0
    for world, policy in policies:
        queries = []
        for knobs, n, seen in ((policy.secondary, 2001, True), (policy.shadow, 1501, False),
                               (other, 0, True), (other, 777, True)):
            origin, direction, tmax = _rays(rng, world.table, n)
            visited = rng.integers(0, 8, n).astype(np.uint64) if seen else None
            queries.append(Query(origin, direction, tmax, knobs, visited))
        args = (world, policy.proxies, policy.modeled)
        together, calls = predict_together(*args, queries, policy.known)
        alone_calls = 0
        for q, got in zip(queries, together, strict=True):
            (want,), c = predict_together(*args, [q], policy.known)
            alone_calls += c
            for f in fields:
                a, b = getattr(want, f), getattr(got, f)
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f
        assert calls <= alone_calls and (calls > 0) == (alone_calls > 0)
        fewer += alone_calls - calls
    assert fewer > 0  # some shard holds no proxy: it makes no call

