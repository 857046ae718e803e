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

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT)
def box_queries(ray, inst, origin, direction, tmax, w2l, bounds):
    """ray (p,) int64, inst (p,) int32 pairs; origin, direction (n, 3) float64 world;
    tmax (n,) float32; w2l (m, 3, 4) float64 world to local; bounds (m, 2, 3) float64 local
    boxes. Returns, per pair: crosses (p,) bool (meets the local box before tmax), internal
    (p,) bool (origin inside), t_box (p,) float64 world t of the query point (entry, or exit
    when internal), length (p,) float64 local units per world unit, point, qdir (p, 3)
    float32 local query point and unit direction (reversed when internal)."""
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
