"""The Wald-style routing step as one kernel: per ray, the owner of the nearest instance box
entered before tmax among shards it has not visited, ties to the lowest owner. It gives
exactly what enumerating every crossing (`InstanceTable.box_entries`) and taking the first
of each ray after a (ray, t_enter, owner) sort gives, with the same slab arithmetic, but
keeps one candidate per ray and culls BVH nodes entered beyond it: a camera ray through a
forest crosses dozens of boxes, and listing and sorting them all cost more than tracing.
The walking kernels (`nprt.workers.kernels.crossings`) run the same search per ray after
their local boxes, culled at the closest hit."""

from __future__ import annotations

import numpy as np
from numba import njit

from nprt.workers.kernels.bvh import JIT, _flat_slabs, _next_leaf, _slab

NONE = -1  # no unvisited box before tmax


@njit(**JIT)
def nearest_owner(origin, direction, tmax, boxes, node_box, node_child, node_start, node_count,
                  prim, cand_owner, cands, cand_flat, cand_bvh, visited):
    """origin (n, 3) float64, direction (n, 3) float32, tmax (n,) float64; boxes and the
    BVH arrays from `bvh_build` (placeholders when not cand_bvh); the candidates as
    `InstanceTable.route_inputs` gives them; visited (n,) uint64 shard bitmask.
    Returns (n,) int32 owner, or NONE."""
    n = origin.shape[0]
    near_t, near_owner = np.full(n, np.inf), np.full(n, NONE, np.int32)
    near_search(origin, direction, tmax, np.ones(n, np.bool_), boxes,
                (node_box, node_child, node_start, node_count, prim), cand_owner, cands,
                cand_flat, cand_bvh, visited, near_t, near_owner)
    return near_owner


# Not inlined: it runs once per batch, and inlined (numba's IR inliner) it cost about 7 s
# of a cold compile in each of its callers (the two walks in `crossings`, and
# `nearest_owner`); 2 cores, 2026-11-27.
@njit(**JIT)
def near_search(origin, direction, lim, active, boxes, bvh, cand_owner, cands, cand_flat,
                cand_bvh, visited, near_t, near_owner):
    """The exact policy's next stop of each active (n,) bool ray: near_t (n,) float64 and
    near_owner (n,) int32 = the entry and owner of the nearest box b with cand_owner[b]
    (m,) int32 >= 0 on a shard not in visited (n,) uint64, crossed before lim (n,)
    float64; on equal entries the lowest owner, as a sort of every crossing on (ray,
    t_enter, owner) picks; inactive rays and rays with none are left as they are.

    Through bvh (`bvh_build`'s arrays over boxes) when cand_bvh, culled at lim and just
    beyond the best so far (rays with a non-finite component take the flat loop: the
    node test does not mirror the slab test's NaN cases); else the slabs of every
    candidate, cands (c,) int64 with boxes cand_flat (6, c) float64, in one flat loop
    (`_flat_slabs`: without NaN handling where no NaN can arise), folded over the crossed
    ones only.
    One loop over the rays, written out here: a helper inlined per ray cost a third more
    (numba counts references on its array arguments at every call)."""
    node_box, node_child, node_start, node_count, prim = bvh
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    te, ok = np.empty(cand_flat.shape[1]), np.empty(cand_flat.shape[1], np.bool_)
    plain = not np.isnan(cand_flat).any()  # `_flat_slabs` may skip NaN handling
    own = np.empty(cands.shape[0], np.int32)  # each candidate's owner, looked up once
    for j in range(cands.shape[0]):
        own[j] = cand_owner[cands[j]]
    for r in range(origin.shape[0]):
        if not active[r]:
            continue
        finite, line = ray_line(origin[r, 0], origin[r, 1], origin[r, 2], direction[r, 0],
                                direction[r, 1], direction[r, 2])
        o0, o1, o2, i0, i1, i2 = line[:6]
        tm, seen = lim[r], visited[r]
        nt, no = np.inf, np.int32(NONE)
        if cand_bvh and finite:
            top, lo, hi = _next_leaf(bvh, stack, -1, line, tm)
            while lo < hi:
                for x in range(lo, hi):
                    b = prim[x]
                    if _unvisited(cand_owner[b], seen):
                        ok_b, te_b, _ = _slab(boxes, b, o0, o1, o2, i0, i1, i2, tm)
                        nt, no = _near_fold(ok_b, te_b, cand_owner[b], nt, no)
                # A node entered after the best so far cannot hold a better box; one
                # entered exactly at it may hold a tie with a lower owner.
                top, lo, hi = _next_leaf(bvh, stack, top, line,
                                         min(tm, np.nextafter(nt, np.inf)))
        else:
            _flat_slabs(cand_flat, plain, o0, o1, o2, i0, i1, i2, tm, te, ok)
            for j in range(cand_flat.shape[1]):
                if ok[j] and _unvisited(own[j], seen):
                    nt, no = _near_fold(True, te[j], own[j], nt, no)
        if no != NONE:
            near_t[r], near_owner[r] = nt, no


@njit(inline="always", **JIT)
def ray_line(o0, o1, o2, d0, d1, d2):
    """A ray as the BVH walk (`bvh._next_leaf`) takes it: (finite, line), line = (o0, o1,
    o2, i0, i1, i2, s0, s1, s2) with i_a = 1 / d_a and s_a = i_a < 0; finite: no component
    of the ray is NaN or inf (the others take the plain loop: the node test does not mirror
    the slab test's NaN cases)."""
    i0, i1, i2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
    finite = (np.isfinite(o0) and np.isfinite(o1) and np.isfinite(o2) and np.isfinite(d0)
              and np.isfinite(d1) and np.isfinite(d2))
    return finite, (o0, o1, o2, i0, i1, i2, int(i0 < 0.0), int(i1 < 0.0), int(i2 < 0.0))


@njit(inline="always", **JIT)
def _unvisited(owner, seen):
    """Whether a box of this owner (-1: not a candidate) is on a shard not in seen."""
    return owner >= 0 and not (seen >> np.uint64(owner)) & np.uint64(1)


@njit(inline="always", **JIT)
def _near_fold(ok, te, owner, nt, no):
    """The nearer of the candidate (nt, no) and a box of `owner` entered at te (if ok):
    smaller entry, on equal entry the lower owner."""
    if ok and (te < nt or (te == nt and owner < no)):
        return te, np.int32(owner)
    return nt, no
