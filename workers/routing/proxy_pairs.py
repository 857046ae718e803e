"""Compiled twins of proxy_query's numpy glue: the local-space box geometry of every (ray,
instance) pair, and the per-ray decision over the proxies' answers (closest confident hit,
open boxes), each in one pass over the pairs. A shard asks about a few hundred pairs a call,
so numpy's dozens of passes and temporaries per call cost as much as the nets.

They give the bits of the numpy formulas they replace (the same operations in the same order,
with numpy's NaN and signed-zero rules); tests/workers/test_proxy_pairs.py keeps those
formulas and compares them pair for pair."""

from __future__ import annotations

import numpy as np
from numba import njit

from nprt.proxies.lineenc import _fmax, _fmin
from nprt.workers.kernels.bvh import _flat_slabs, _next_leaf, _slab
from nprt.workers.kernels.nearest import ray_line

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT)
def walk_queries(origin, direction, tmax, world_boxes, bvh, col_of, members, flat, owner,
                 visited, use_visited, w2l, bounds, mesh_of, has_m):
    """`InstanceTable.box_entries` of the rays against the boxes `members` (k,) int64 (the
    same world slab test, crossings ray-major and then in the order of `members`), less
    the boxes on shards in visited (n,) uint64 (when use_visited; owner (m,) int32), then
    `box_queries` of each crossing, in one pass: the pairs whose local box the ray crosses
    (the only ones `decide` and the nets look at), and nothing else.

    origin (n, 3) float64, direction (n, 3) float32 or float64 (a float32 one is read as
    its float64 values: a copy per call saved); tmax (n,) float32; world_boxes (m, 2, 3)
    float64. flat (6, k) float64, the members' boxes as rows lo x, y, z, hi x, y, z, or
    (6, 0): with columns, every ray tests all of them in one branch-free loop that
    vectorises (the local walk's `FLAT_WALK_MAX` choice; the slab test's crossings). Else bvh
    (`bvh_build`'s arrays over world_boxes) is walked when col_of (m,) int32 (each box's
    position in members, -1: not asked) has any entry >= 0, else a plain loop; w2l,
    bounds as in `box_queries`; mesh_of (m,) int32 base mesh of each instance, has_m
    (meshes,) bool (a proxy answers for it). Returns, per kept pair: ray (p,) int64, inst
    (p,) int32, mesh (p,) int64, has (p,) bool, and box_queries' internal, t_box, length,
    point, qdir; then the pairs with has grouped by mesh, in pair order within a mesh:
    grouped (a,) int64 pair rows, mesh m's at grouped[start[m]:start[m + 1]], start
    (meshes + 1,) int64."""
    n, k = origin.shape[0], members.shape[0]
    node_box, node_child, node_start, node_count, prim = bvh
    use_flat = flat.shape[1] > 0
    walk = not use_flat and col_of.shape[0] > 0 and node_child.shape[0] > 0
    plain = use_flat and not np.isnan(flat).any()  # `_flat_slabs` may skip NaN handling
    f_te, f_ok = np.empty(flat.shape[1]), np.empty(flat.shape[1], np.bool_)
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    hit_col = np.empty(k, np.int64)  # one ray's crossings, by position in members
    cap = 4 * n + k + 16
    ray, inst = np.empty(cap, np.int64), np.empty(cap, np.int32)
    p = 0
    for r in range(n):
        if p + k > cap:
            cap = 2 * cap + k
            ray, inst = _grow(ray, p, cap), _grow(inst, p, cap)
        finite, line = ray_line(origin[r, 0], origin[r, 1], origin[r, 2], direction[r, 0],
                                direction[r, 1], direction[r, 2])
        o0, o1, o2, i0, i1, i2 = line[:6]
        tm = np.float64(tmax[r])
        seen = visited[r] if use_visited else np.uint64(0)
        h = 0
        if use_flat:  # crossings come out in position order
            _flat_slabs(flat, plain, o0, o1, o2, i0, i1, i2, tm, f_te, f_ok)
            for j in range(k):
                if f_ok[j] and not (seen >> np.uint64(owner[members[j]])) & np.uint64(1):
                    hit_col[h] = j
                    h += 1
        elif walk and finite:
            top, lo, hi = _next_leaf(bvh, stack, -1, line, tm)
            while lo < hi:
                for x in range(lo, hi):
                    b = prim[x]
                    j = col_of[b]
                    if j < 0 or (seen >> np.uint64(owner[b])) & np.uint64(1):
                        continue
                    if _slab(world_boxes, b, o0, o1, o2, i0, i1, i2, tm)[0]:
                        y = h  # insert by position: a ray crosses few boxes
                        while y > 0 and hit_col[y - 1] > j:
                            hit_col[y] = hit_col[y - 1]
                            y -= 1
                        hit_col[y] = j
                        h += 1
                top, lo, hi = _next_leaf(bvh, stack, top, line, tm)
        else:
            for j in range(k):
                b = members[j]
                if (seen >> np.uint64(owner[b])) & np.uint64(1):
                    continue
                if _slab(world_boxes, b, o0, o1, o2, i0, i1, i2, tm)[0]:
                    hit_col[h] = j
                    h += 1
        for y in range(h):
            ray[p], inst[p] = r, members[hit_col[y]]
            p += 1
    ray, inst = ray[:p], inst[:p]
    crosses, internal, t_box, length, point, qdir = box_queries(ray, inst, origin, direction,
                                                                tmax, w2l, bounds)
    keep = np.flatnonzero(crosses)
    inst = inst[keep]
    mesh = np.empty(len(keep), np.int64)
    has = np.empty(len(keep), np.bool_)
    start = np.zeros(has_m.shape[0] + 1, np.int64)  # asked pairs per mesh, then offsets
    for q in range(len(keep)):
        mesh[q] = mesh_of[inst[q]]
        has[q] = has_m[mesh[q]]
        if has[q]:
            start[mesh[q] + 1] += 1
    for m in range(has_m.shape[0]):
        start[m + 1] += start[m]
    grouped = np.empty(start[-1], np.int64)
    fill = start[:-1].copy()
    for q in range(len(keep)):
        if has[q]:
            grouped[fill[mesh[q]]] = q
            fill[mesh[q]] += 1
    return (ray[keep], inst, mesh, has, internal[keep], t_box[keep], length[keep],
            point[keep], qdir[keep], grouped, start)


@njit(**JIT)
def _grow(a, p, cap):
    """a's first p entries in a new array of cap entries."""
    b = np.empty(cap, a.dtype)
    b[:p] = a[:p]
    return b


@njit(**JIT)
def box_queries(ray, inst, origin, direction, tmax, w2l, bounds):
    """ray (p,) int64, inst (p,) int32 pairs; origin (n, 3) float64 and direction (n, 3)
    float64 or float32 world; tmax (n,) float32; w2l (m, 3, 4) float64 world to local;
    bounds (m, 2, 3) float64 local boxes. Returns, per pair: crosses (p,) bool (meets the
    local box before tmax), internal (p,) bool (origin inside), t_box (p,) float64 world t
    of the query point (entry, or exit when internal), length (p,) float64 local units per
    world unit, point, qdir (p, 3) float32 local query point and unit direction (reversed
    when internal)."""
    p = len(inst)
    crosses = np.empty(p, np.bool_)
    internal = np.empty(p, np.bool_)
    t_box = np.empty(p)
    length = np.empty(p)
    point = np.empty((p, 3), np.float32)
    qdir = np.empty((p, 3), np.float32)
    o = np.empty(3)
    d = np.empty(3)
    for k in range(p):
        i, r = inst[k], ray[k]
        for a in range(3):
            # np.einsum("pij,pj->pi")'s order on this numpy, (x0 + x2) + x1 (two lanes),
            # added to its zeroed output (so a zero sum is +0.0)
            o[a] = (0.0 + ((w2l[i, a, 0] * origin[r, 0] + w2l[i, a, 2] * origin[r, 2])
                           + w2l[i, a, 1] * origin[r, 1])) + w2l[i, a, 3]
            d[a] = 0.0 + ((w2l[i, a, 0] * direction[r, 0] + w2l[i, a, 2] * direction[r, 2])
                          + w2l[i, a, 1] * direction[r, 1])
        t_enter = 0.0
        t_exit = 0.0
        for a in range(3):
            inv = 1.0 / d[a]
            t0 = (bounds[i, 0, a] - o[a]) * inv
            t1 = (bounds[i, 1, a] - o[a]) * inv
            lo, hi = _fmin(t0, t1), _fmax(t0, t1)
            t_enter = lo if a == 0 else _fmax(t_enter, lo)
            t_exit = hi if a == 0 else _fmin(t_exit, hi)
        # np.maximum(t_enter, 0.0): NaN stays NaN, so a NaN entry never crosses
        floor = t_enter if (t_enter != t_enter or t_enter >= 0.0) else 0.0
        crosses[k] = (t_exit >= floor) and (t_enter < tmax[r])
        inner = t_enter <= 0.0
        internal[k] = inner
        tb = t_exit if inner else t_enter
        t_box[k] = tb
        sq = d[0] * d[0]  # np.linalg.norm: add.reduce of the squares, in axis order
        sq += d[1] * d[1]
        sq += d[2] * d[2]
        norm = np.sqrt(sq)
        length[k] = norm
        div = norm if norm > 0 else 1.0  # sampling.normalize: zero vectors stay zero
        for a in range(3):
            point[k, a] = np.float32(o[a] + tb * d[a])
            u = d[a] / div
            qdir[k, a] = np.float32(-u if inner else u)
    return crosses, internal, t_box, length, point, qdir


@njit(**JIT)
def decide(ray, inst, mesh, crosses, internal, t_box, length, tmax, asked, has, vis, tp,
           thr_m, band_m, margin_m, best_t, best_i):
    """The external / internal rules of section 5.2 per pair, then per ray the closest
    confident hit and the open boxes (proxy_query.predict's Prediction fields).

    Per pair (p,): ray int64, inst int32, mesh int64, crosses, internal bool, t_box, length
    float64, tmax float32 (the ray's), asked bool (the nets answered it), has bool (crosses
    and its mesh has a proxy), vis float32, tp float32 (the proxy's t, inf where not
    evaluated). Per mesh: thr_m float32 threshold, band_m float64 band, margin_m float64
    internal margin in local units. best_t (n,) float32, best_i (n,) int32: the known exact
    hits, lowered in place to the closest confident one (ties: the known hit, then the lowest
    instance). Returns internal_win, uncertain, ambiguous (n,) bool and first_open (n,) int32.

    A pair `has` but not `asked` was skipped: its box entry lies beyond a hit already found,
    so it can neither win nor be open."""
    n = len(best_t)
    pt = np.full(n, np.inf, np.float32)  # per ray, the closest confident proxy hit
    pi = np.full(n, -1, np.int32)
    pin = np.zeros(n, np.bool_)
    inner_hits = np.zeros(n, np.int64)
    unsure = np.zeros(len(ray), np.bool_)
    for k in range(len(ray)):
        if not asked[k]:
            continue
        inner = internal[k]
        v, thr = vis[k], thr_m[mesh[k]]
        t_proxy = np.float64(tp[k]) / length[k]
        margin = margin_m[mesh[k]] / length[k]
        near_origin = inner and v >= thr and abs(t_proxy - t_box[k]) < margin
        u = abs(np.float32(v - thr)) < band_m[mesh[k]] or near_origin
        unsure[k] = u
        if u or not v >= thr or (inner and not t_proxy <= t_box[k]):
            continue
        t = np.float32(t_box[k] - t_proxy if inner else t_box[k] + t_proxy)
        if not t < tmax[k]:
            continue
        r = ray[k]
        if inner:
            inner_hits[r] += 1
        if t < pt[r] or (t == pt[r] and inst[k] < pi[r]):
            pt[r], pi[r], pin[r] = t, inst[k], inner
    internal_win = np.zeros(n, np.bool_)
    for r in range(n):
        if pt[r] < best_t[r]:
            best_t[r], best_i[r], internal_win[r] = pt[r], pi[r], pin[r]
    # A box no proxy answers with confidence matters only if entered before the best hit.
    uncertain = np.zeros(n, np.bool_)
    first_open = np.full(n, -1, np.int32)
    first_t = np.full(n, np.inf)
    for k in range(len(ray)):
        if not (unsure[k] or (crosses[k] and not has[k])):
            continue
        r = ray[k]
        t_enter = 0.0 if internal[k] else t_box[k]
        if not t_enter < best_t[r]:
            continue
        if not uncertain[r] or t_enter < first_t[r] or (
                t_enter == first_t[r] and inst[k] < first_open[r]):
            first_t[r], first_open[r] = t_enter, inst[k]
        uncertain[r] = True
    ambiguous = inner_hits - internal_win.astype(np.int64) > 0
    return internal_win, uncertain, ambiguous, first_open


@njit(**JIT)
def decide_queries(off, cut, ray, inst, mesh, internal, t_box, length, tmax, has, vis, tp,
                   thr_q, band_q, margin_q, exact_if_ambiguous, best_t, best_i):
    """`decide` of each query of a `predict_together` call, in one call: query j's rays are
    off[j]:off[j + 1] of best_t (n,) float32 / best_i (n,) int32 (lowered in place) and tmax
    (n,) float32, its pairs cut[j]:cut[j + 1] (pairs come ray-major; ray (p,) int64 over all
    rays), its knobs row j of thr_q (q, meshes) float32, band_q and margin_q (q, meshes)
    float64, and exact_if_ambiguous (q,) bool (its ambiguous rays are uncertain). Every pair
    crosses; asked = has. Returns internal_win, uncertain, ambiguous (n,) bool and
    first_open (n,) int32, nothing for a query without pairs."""
    n = len(best_t)
    internal_win = np.zeros(n, np.bool_)
    uncertain = np.zeros(n, np.bool_)
    ambiguous = np.zeros(n, np.bool_)
    first_open = np.full(n, -1, np.int32)
    for j in range(len(off) - 1):
        a, b, r0, r1 = cut[j], cut[j + 1], off[j], off[j + 1]
        if a == b:
            continue
        r = ray[a:b] - r0
        tm = np.empty(b - a, np.float32)  # each pair's ray's tmax
        for k in range(b - a):
            tm[k] = tmax[r0 + r[k]]
        w, u, g, f = decide(r, inst[a:b], mesh[a:b], np.ones(b - a, np.bool_), internal[a:b],
                            t_box[a:b], length[a:b], tm, has[a:b], has[a:b], vis[a:b], tp[a:b],
                            thr_q[j], band_q[j], margin_q[j], best_t[r0:r1], best_i[r0:r1])
        if exact_if_ambiguous[j]:
            u |= g
        internal_win[r0:r1], uncertain[r0:r1] = w, u
        ambiguous[r0:r1], first_open[r0:r1] = g, f
    return internal_win, uncertain, ambiguous, first_open
