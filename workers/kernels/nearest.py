"""The Wald-style routing step as one kernel: per ray, the owner of the nearest instance box
entered before tmax among shards it has not visited, ties to the lowest owner. It gives
exactly what enumerating every crossing (`InstanceTable.box_entries`) and taking the first
of each ray after a (ray, t_enter, owner) sort gives, with the same slab arithmetic, but
keeps one candidate per ray and culls BVH nodes entered beyond it: a camera ray through a
forest crosses dozens of boxes, and listing and sorting them all cost more than tracing."""

from __future__ import annotations

import numpy as np
from numba import njit

from nprt.workers.kernels.bvh import JIT, _push_near, _push_pair, _slab

NONE = -1  # no unvisited box before tmax


@njit(**JIT)
def bvh_nearest_owner(origin, direction, tmax, boxes, node_box, node_child, node_start,
                      node_count, prim, in_set, box_owner, visited, stack):
    """origin (n, 3) float64, direction (n, 3) float64, tmax (n,) float64; boxes and the
    BVH arrays from `bvh_build`; in_set (m,) bool: boxes to consider; box_owner (m,) int32
    shard of each box; visited (n,) uint64 shard bitmask; stack (nodes + 1,) int32 scratch.
    Returns (n,) int32 owner, or NONE.

    Nodes are visited nearer child first, so the first candidate found is usually the
    nearest and the rest of the tree is culled at it; the answer, a minimum, does not
    depend on the order."""
    n = origin.shape[0]
    out = np.full(n, NONE, np.int32)
    stack_t = np.empty(stack.shape[0])
    for r in range(n):
        o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
        d0, d1, d2 = direction[r, 0], direction[r, 1], direction[r, 2]
        i0, i1, i2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
        s0, s1, s2 = int(i0 < 0.0), int(i1 < 0.0), int(i2 < 0.0)
        tm = tmax[r]
        seen = visited[r]
        best_t, best_o = np.inf, NONE
        if not (np.isfinite(o0) and np.isfinite(o1) and np.isfinite(o2) and np.isfinite(d0)
                and np.isfinite(d1) and np.isfinite(d2)):
            for b in range(boxes.shape[0]):  # the node test does not mirror NaN cases
                best_t, best_o = _consider(boxes, b, in_set, box_owner, seen, o0, o1, o2,
                                           i0, i1, i2, tm, best_t, best_o)
            out[r] = best_o
            continue
        # A node entered after the best so far cannot hold a better box; one entered
        # exactly at it may hold a tie with a lower owner (hence <=, in `_push_*`). A node
        # is entered no later than any box below it, and a box passing the slab test
        # before tm is entered before tm.
        top = _push_near(node_box, 0, stack, stack_t, 0, o0, o1, o2, i0, i1, i2, s0, s1, s2,
                         tm)
        while top > 0:
            top -= 1
            if not stack_t[top] <= min(tm, best_t):
                continue  # culled since it was pushed
            node = stack[top]
            c = node_child[node]
            if c >= 0:
                top = _push_pair(node_box, c, stack, stack_t, top, o0, o1, o2, i0, i1, i2,
                                 s0, s1, s2, min(tm, best_t))
                continue
            for x in range(node_start[node], node_start[node] + node_count[node]):
                best_t, best_o = _consider(boxes, prim[x], in_set, box_owner, seen, o0, o1,
                                           o2, i0, i1, i2, tm, best_t, best_o)
        out[r] = best_o
    return out


@njit(inline="always", **JIT)
def _consider(boxes, b, in_set, box_owner, seen, o0, o1, o2, i0, i1, i2, tm, best_t, best_o):
    if not in_set[b]:
        return best_t, best_o
    owner = box_owner[b]
    if owner < 0 or (seen >> np.uint64(owner)) & np.uint64(1):
        return best_t, best_o
    ok, te, _ = _slab(boxes, b, o0, o1, o2, i0, i1, i2, tm)
    if ok and (te < best_t or (te == best_t and owner < best_o)):
        return te, owner
    return best_t, best_o
