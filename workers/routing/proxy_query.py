"""Neural-proxy intersection of rays with instance boxes this shard does not hold
(paper section 5): box entry point in local space, the visibility and depth nets, and
the external / internal cases of section 5.2."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from nprt.workers.kernels.bvh import bvh_build
from nprt.workers.routing import net_rows, proxy_pairs
from nprt.workers.traversal.toplevel import FLAT_WALK_MAX, flat_rows
from nprt.workers.wavefront.world import ShardWorld


@dataclass(frozen=True)
class Prediction:
    """Per ray: t (n,) float32 closest confident predicted hit (inf if none), inst (n,)
    int32 (-1), uncertain (n,) bool (the ray enters a box whose visibility is within the
    band, or that has no proxy, before its closest confident hit), internal (n,) bool (the
    predicted hit is a proxy's answer for a box the ray starts inside: the paper's internal
    case, whose t is the surface nearest the box exit, not the first one from the origin),
    ambiguous (n,) bool (a ray also confidently hits a box it starts inside, other than the
    chosen one: its first surface there may come before the chosen hit), first_open (n,)
    int32 (of the boxes that make a ray uncertain, the one it enters first; -1: none, or
    uncertain only for ambiguity; visiting its owner settles it exactly). A prediction
    inside the band, or an internal one within the internal margin of the origin, is never
    a hit. Per (ray, box) pair a proxy was asked about, grouped by base mesh in increasing
    order (pair order within a mesh: ray-major, then the order of the instances asked
    about): asked_ray (p,) int64 row, asked_mesh (p,) int64 base mesh (what the accuracy
    prediction counts)."""

    t: np.ndarray
    inst: np.ndarray
    uncertain: np.ndarray
    internal: np.ndarray
    ambiguous: np.ndarray
    first_open: np.ndarray
    asked_ray: np.ndarray
    asked_mesh: np.ndarray


@dataclass(frozen=True)
class QueryKnobs:
    """How one ray kind trusts the proxies. threshold None: each proxy's own (calibrated at
    training); band : (meshes,) float64 confidence band per base mesh; internal_margin: a
    confident internal answer whose surface lies within this fraction of the proxy's held-out
    p90 depth error of the origin is unsure (0 keeps the paper's rule); exact_if_ambiguous:
    Prediction.ambiguous rays are uncertain."""

    threshold: float | None
    band: np.ndarray
    internal_margin: float = 0.0
    exact_if_ambiguous: bool = True


@dataclass(frozen=True)
class Query:
    """One ray kind's questions for `predict_together`: origin (n, 3) float64 (or float32),
    direction (n, 3) float32 world, tmax (n,) float32, knobs, visited (n,) uint64 or None
    (as `predict`'s)."""

    origin: np.ndarray
    direction: np.ndarray
    tmax: np.ndarray
    knobs: QueryKnobs
    visited: np.ndarray | None = None


def predict(world: ShardWorld, proxies: dict, remote: np.ndarray, origin: np.ndarray,
            direction: np.ndarray, tmax: np.ndarray, knobs: QueryKnobs, known=None,
            visited: np.ndarray | None = None) -> Prediction:
    """origin (n, 3) float64 (or float32), direction (n, 3) float32 world; tmax (n,) float32;
    remote (m,) int32: the instances to ask proxies about; known: LocalGeometry of other
    remote instances, intersected exactly; visited: (n,) uint64 shard bitmask of each ray,
    whose shards' boxes are not asked about (their geometry was intersected exactly, and the
    ray carries what it found)."""
    preds, _ = predict_together(world, proxies, remote,
                                [Query(origin, direction, tmax, knobs, visited)], known)
    return preds[0]


def predict_together(world: ShardWorld, proxies: dict, remote: np.ndarray,
                     queries: list[Query], known=None) -> tuple[list[Prediction], int]:
    """`predict` of each query, with one walk and one call of each mesh's nets for all of
    them (a net call costs about 45 us whatever its rows: a step's secondary and shadow rays
    are asked together). A ray's answers do not depend on the other rays of its call
    (`Proxy.run`), so each Prediction is the one `predict` gives for its query alone.
    Returns the Predictions and the onnxruntime calls made."""
    sizes = [len(q.origin) for q in queries]
    off = np.zeros(len(sizes) + 1, np.int64)
    np.cumsum(sizes, out=off[1:])
    one = len(queries) == 1

    def joined(field, dtype):
        if one:
            return np.ascontiguousarray(getattr(queries[0], field), dtype)
        return np.concatenate([np.asarray(getattr(q, field), dtype) for q in queries])

    origin, direction = joined("origin", np.float64), joined("direction", np.float32)
    tmax = joined("tmax", np.float32)
    best_t, best_i = known_hits(known, origin, direction, tmax)
    table = world.table
    banks = [_bank(proxies, q.knobs, table.n_mesh) for q in queries]
    if off[-1] == 0 or len(remote) == 0:
        return [nothing_asked(best_t[a:b], best_i[a:b])
                for a, b in zip(off[:-1], off[1:], strict=True)], 0
    boxes, bvh, col_of, members, flat, ids, owner, w2l, bounds, mesh_of = _walk_inputs(
        table, world.owner, remote)
    use_visited = any(q.visited is not None for q in queries)
    visited = np.zeros(0, np.uint64)
    if use_visited:  # a query without one has visited nothing
        visited = np.concatenate([np.zeros(n, np.uint64) if q.visited is None
                                  else np.asarray(q.visited, np.uint64)
                                  for q, n in zip(queries, sizes, strict=True)])
    # The crossed boxes and their local-space geometry in one walk; only the nets run per
    # mesh. Pairs whose local box the ray misses are dropped there: no rule looks at them.
    (ray, inst, mesh, has, internal, t_box, length, point, qdir, grouped,
     start) = proxy_pairs.walk_queries(
        origin, direction, tmax, boxes, bvh, col_of, members, flat, owner, visited,
        use_visited, w2l, bounds, mesh_of, banks[0].has)
    inst = ids[inst]  # positions in the asked set -> instance ids
    # Pairs come ray-major: each query's are a slice, and each its own threshold.
    cut = np.searchsorted(ray, off)
    thr_q, band_q, margin_q, amb_q = _stacked(banks, queries)
    vis, tp, calls = _ask_nets(banks[0], len(ray), grouped, start, point, qdir, thr_q, cut,
                               mesh)
    # An internal t is the surface nearest the box exit; the ray's first surface in that box
    # lies anywhere in (0, t]. Any internal hit that did not win may hide a nearer surface.
    internal_win, uncertain, ambiguous, first_open = proxy_pairs.decide_queries(
        off, cut, ray, inst, mesh, internal, t_box, length, tmax, has, vis, tp, thr_q, band_q,
        margin_q, amb_q, best_t, best_i)
    out = []
    for j in range(len(queries)):
        a, b, r0, r1 = cut[j], cut[j + 1], off[j], off[j + 1]
        mine = grouped if one else grouped[(grouped >= a) & (grouped < b)]
        out.append(Prediction(best_t[r0:r1], best_i[r0:r1], uncertain[r0:r1],
                              internal_win[r0:r1], ambiguous[r0:r1], first_open[r0:r1],
                              ray[mine] - r0, mesh[mine]))
    return out, calls


# (banks' ids, exact_if_ambiguous) -> (the banks, kept so that their ids stay theirs,
# `_stacked`'s arrays)
_STACKED: dict = {}


def _stacked(banks: list, queries: list) -> tuple:
    """Per query j: thr_q (q, meshes) float32, band_q, margin_q (q, meshes) float64 and
    exact_if_ambiguous (q,) bool, as `proxy_pairs.decide_queries` takes them (a shard asks
    with the same banks at every step: kept)."""
    amb = tuple(bool(q.knobs.exact_if_ambiguous) for q in queries)
    key = (tuple(id(b) for b in banks), amb)
    got = _STACKED.get(key)
    if got is not None:
        return got[1]
    arrays = (np.stack([b.thr for b in banks]), np.stack([b.band for b in banks]),
              np.stack([b.margin for b in banks]), np.array(amb, bool))
    if len(_STACKED) >= 64:  # a few shards' banks in one process; jobs replace them
        _STACKED.clear()
    _STACKED[key] = (tuple(banks), arrays)
    return arrays


# id(table) -> (weak reference to the table, {asked set's bytes: `_walk_inputs`' tuple})
_WALKS: dict = {}


def _walk_inputs(table, owner: np.ndarray, remote: np.ndarray) -> tuple:
    """`walk_queries`' arrays for the instances remote (k,) of table, restricted to them:
    their world boxes (k, 2, 3) and a BVH over those alone (the table's BVH also holds this
    shard's boxes, which the walk would visit only to skip: 10-20 % of the walk's CPU at
    K = 8), col_of and members the positions 0..k-1, flat (6, k) float64 the boxes for the
    walk's flat loop where k <= FLAT_WALK_MAX or there is no BVH ((6, 0): walk the BVH),
    ids (k,) int32 each position's instance id (walk_queries' inst are positions), owner,
    w2l, bounds and mesh_of of those ids. Every way meets the same boxes in the same
    order: crossings are sorted by position, and a box passing the slab test is reached
    through any BVH over it (`bvh._node_hit`).

    The flat loop, as in the local walk: `bench_proxy_walk` replays a render's walks both
    ways (the same pairs), flat over BVH CPU 0.54x / 0.71x in city at K = 2 / 8 (36 / 62
    remote boxes at most), 0.60x / 0.74x in forest and windy (46 / 68), 0.49-0.50x on the
    held-out foliage scene (12-14 interpenetrating boxes, whose BVH nodes overlap and cull
    little; bench/README.md, "The proxy walk's flat loop"). Above FLAT_WALK_MAX the BVH,
    as in the local walk (not measured for this walk). Kept per table, set and owners: a
    shard asks about the same instances at every step."""
    got = _WALKS.get(id(table))
    if got is None or got[0]() is not table:
        key = id(table)
        got = _WALKS[key] = (weakref.ref(table, lambda _, key=key: _WALKS.pop(key, None)), {})
    remote = np.asarray(remote).astype(np.int64)
    which = remote.tobytes() + np.asarray(owner)[remote].astype(np.int64).tobytes()
    hit = got[1].get(which)
    if hit is not None:
        return hit
    boxes, bvh, col_of, members, w2l, bounds, mesh_of = table.pair_inputs(remote)
    ids = np.array(members, np.int32)
    boxes = np.ascontiguousarray(boxes[ids])
    members = np.arange(len(ids), dtype=np.int64)
    flat = np.zeros((6, 0))
    if len(col_of) and len(ids) > FLAT_WALK_MAX:
        bvh = bvh_build(boxes)
        col_of = np.arange(len(ids), dtype=np.int32)
    else:  # one flat loop over the members' boxes; no BVH
        flat = flat_rows(boxes)
        col_of = np.zeros(0, np.int32)
    hit = (boxes, bvh, col_of, members, flat, ids,
           np.ascontiguousarray(owner[ids], np.int32),
           np.ascontiguousarray(w2l[ids]), np.ascontiguousarray(bounds[ids]),
           np.ascontiguousarray(mesh_of[ids]))
    if len(got[1]) >= 8:  # a shard asks about one or two sets
        got[1].clear()
    got[1][which] = hit
    return hit


@dataclass(frozen=True)
class _Bank:
    """What `predict` reads per base mesh, for one proxies dict and one QueryKnobs (built
    once: a shard asks with the same two at every step). proxy (meshes,) the Proxy or None;
    has (meshes,) bool (a proxy answers for it); thr (meshes,) float32 visibility threshold;
    band (meshes,) float64; margin (meshes,) float64 internal margin in local units before
    dividing by the pair's length (world to local scale); line: every proxy uses the "line"
    encoding, whose float32 box constants (`Proxy.line_constants`) are stacked by mesh in
    consts: lo, hi, centre (meshes, 3), half, scale (meshes,), depth centre (meshes, 3)."""

    proxy: list
    has: np.ndarray
    thr: np.ndarray
    band: np.ndarray
    margin: np.ndarray
    line: bool
    consts: tuple


# knobs id -> (weak reference to the knobs, (meshes, proxies' ids), _Bank). An entry goes
# with its knobs (a policy's), so a pool that outlives jobs does not keep their proxies.
_BANKS: dict = {}


def _bank(proxies: dict, knobs: QueryKnobs, n_mesh: int) -> _Bank:
    which = (n_mesh, tuple((m, id(p)) for m, p in proxies.items()))
    got = _BANKS.get(id(knobs))
    if got is not None and got[0]() is knobs and got[1] == which:
        return got[2]
    proxy = [None] * n_mesh
    thr = np.zeros(n_mesh, np.float32)
    margin = np.zeros(n_mesh)
    has = np.zeros(n_mesh, bool)
    consts = [np.zeros((n_mesh, 3), np.float32), np.zeros((n_mesh, 3), np.float32),
              np.zeros((n_mesh, 3), np.float32), np.zeros(n_mesh, np.float32),
              np.zeros(n_mesh, np.float32), np.zeros((n_mesh, 3), np.float32)]
    line = True
    for m, p in proxies.items():
        if m >= n_mesh:
            continue
        proxy[m], has[m] = p, True
        thr[m] = p.meta["threshold"] if knobs.threshold is None else knobs.threshold
        p90 = p.meta.get("report", {}).get("depth_err_rel_p90", 0.0)
        margin[m] = knobs.internal_margin * p90 * float(p.diag)
        line = line and p.meta["encoding"] == "line"
        if line:
            for c, v in zip(consts, p.line_constants(), strict=True):
                c[m] = v
    bank = _Bank(proxy, has, thr, np.ascontiguousarray(knobs.band, np.float64), margin, line,
                 tuple(consts))
    key = id(knobs)
    _BANKS[key] = (weakref.ref(knobs, lambda _, key=key: _BANKS.pop(key, None)), which, bank)
    return bank


def _ask_nets(bank: _Bank, p: int, grouped: np.ndarray, start: np.ndarray, point, qdir,
              thr_q: np.ndarray, cut: np.ndarray, mesh: np.ndarray):
    """Each mesh's nets on its pairs, mesh m's pair rows at grouped[start[m]:start[m + 1]]
    (pair order within a mesh), each pair's visibility threshold thr_q[j, mesh of the pair]
    for the pairs cut[j]:cut[j + 1] of query j (thr_q (q, meshes) float32): vis (p,)
    float32 (0 where not asked) and tp (p,) float32 the proxy's t in local units (inf where
    not asked or below the threshold), and the onnxruntime calls made. The "line" encoding
    of every mesh's pairs is compiled passes around the nets (`net_rows`: the bits of
    Proxy.query, mesh by mesh)."""
    rows = grouped
    if not len(rows):
        return np.zeros(p, np.float32), np.full(p, np.inf, np.float32), 0
    if not bank.line:
        vis = np.zeros(p, np.float32)
        tp = np.full(p, np.inf, np.float32)
        thr = np.concatenate([thr_q[j, mesh[cut[j]:cut[j + 1]]] for j in range(len(thr_q))])
        calls = 0
        for m in np.flatnonzero(np.diff(start)):
            s, e = int(start[m]), int(start[m + 1])
            sel = rows[s:e]
            low = float(thr[sel].min())  # depth where any query's threshold is reached
            v, t = bank.proxy[m].query(point[sel], qdir[sel], min_visibility=low)
            vis[sel], tp[sel] = v, np.where(v >= thr[sel], t, np.inf)
            calls += bank.proxy[m].calls(e - s) + bank.proxy[m].calls(int((v >= low).sum()))
        return vis, tp, calls
    lo, hi, centre, half, scale, dcentre = bank.consts
    x, on_box, shift, at = net_rows.net_inputs(lo, hi, centre, half, start, grouped, point, qdir)
    v = np.empty(len(x), np.float32)
    calls = _run_blocks(bank.proxy, "visibility", x, at, v)
    # The depth net runs where visibility reaches the threshold: those rows gathered, each
    # mesh's still one block (the same rows, in the same order, as mesh by mesh).
    x_deep, dat, deep = net_rows.deep_inputs(v, thr_q, cut, mesh, start, grouped, at, x)
    y = np.empty(len(x_deep), np.float32)
    calls += _run_blocks(bank.proxy, "depth", x_deep, dat, y)
    vis, tp = net_rows.net_answers(p, start, grouped, at, v, deep, y, on_box, shift, qdir,
                                   scale, dcentre)
    return vis, tp, calls


def _run_blocks(proxy: list, net: str, x: np.ndarray, at: np.ndarray, out: np.ndarray) -> int:
    """out[at[m]:at[m + 1]] = mesh m's net on x's rows there (each block of an even count,
    `net_rows`), for every mesh with rows; returns the onnxruntime calls made."""
    calls = 0
    bounds = at.tolist()
    for m in np.flatnonzero(at[1:] > at[:-1]).tolist():
        s, e = bounds[m], bounds[m + 1]
        out[s:e] = proxy[m].run_even(net, x[s:e])
        calls += proxy[m].calls(e - s)
    return calls


def nothing_asked(best_t: np.ndarray, best_i: np.ndarray) -> Prediction:
    """The Prediction of rays no proxy was asked about: only their known hits."""
    n, none = len(best_t), np.zeros(0, np.int64)
    return Prediction(best_t, best_i, np.zeros(n, bool), np.zeros(n, bool),
                      np.zeros(n, bool), np.full(n, -1, np.int32), none, none)


def known_hits(known, origin, direction, tmax):
    """(n,) float32 t and (n,) int32 instance of the closest exact hit among `known`."""
    n = len(origin)
    best_t = np.full(n, np.inf, np.float32)
    best_i = np.full(n, -1, np.int32)
    if known is not None and len(known.instances) and n:
        t, inst, _, _, _ = known.intersect_closest(origin, direction, tmax)
        hit = inst >= 0
        best_t[hit], best_i[hit] = t[hit], inst[hit]
    return best_t, best_i
