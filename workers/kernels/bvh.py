"""Jitted top-level kernels: a binned-SAH BVH over instance boxes (built once per scene),
and the float64 slab test of rays against instance boxes, with exactly the crossings,
order and t values of the numpy reference formula (see `InstanceTable.box_entries`)."""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

# Instances per BVH leaf. Leaves are tested with the exact formula, inner nodes only cull.
BVH_LEAF_SIZE = 2
# error_model="numpy": 1 / 0.0 is inf (as in numpy), not a ZeroDivisionError.
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(inline="always", **JIT)
def _fmin(a, b):
    """np.fmin: NaN loses; on a tie the first operand (numpy's own sign of a zero tie
    depends on the array length, so only values are promised)."""
    return b if (b < a or a != a) else a


@njit(inline="always", **JIT)
def _fmax(a, b):
    return b if (b > a or a != a) else a


@njit(inline="always", **JIT)
def _slab(boxes, j, o0, o1, o2, i0, i1, i2, tmax):
    """The reference slab test of one ray against boxes[j] (2, 3) float64: per axis
    fmin/fmax of (plane - o) * inv, then fmax/fmin over axes 0, 1, 2 in order.
    Returns (crossed, t_enter, t_exit). Boxes are indexed, not sliced: a view per box
    costs two atomic reference counts, more than the test itself."""
    return _slab_planes(boxes[j, 0, 0], boxes[j, 0, 1], boxes[j, 0, 2], boxes[j, 1, 0],
                        boxes[j, 1, 1], boxes[j, 1, 2], o0, o1, o2, i0, i1, i2, tmax)


@njit(inline="always", **JIT)
def _slab_planes(lo0, lo1, lo2, hi0, hi1, hi2, o0, o1, o2, i0, i1, i2, tmax):
    """`_slab` of the box lo, hi; branch-free, so a loop over boxes vectorises."""
    return _slab_by(_fmin, _fmax, lo0, lo1, lo2, hi0, hi1, hi2, o0, o1, o2, i0, i1, i2, tmax)


@njit(inline="always", **JIT)
def _slab_planes_finite(lo0, lo1, lo2, hi0, hi1, hi2, o0, o1, o2, i0, i1, i2, tmax):
    """`_slab_planes` where no product can be NaN (finite origin and 1 / direction, box
    planes not NaN): then fmin / fmax are plain min / max and give the same values (only
    the sign of a zero tie may differ, and every use of t compares it), and the loop over
    boxes vectorises without the NaN masks."""
    return _slab_by(_min, _max, lo0, lo1, lo2, hi0, hi1, hi2, o0, o1, o2, i0, i1, i2, tmax)


@njit(inline="always", **JIT)
def _flat_slabs(flat, plain, o0, o1, o2, i0, i1, i2, tmax, te, ok):
    """The slab tests of every box in flat against the ray, in one branch-free loop (it
    vectorises): ok[j] box j is crossed before tmax, te[j] its entry (scratch (k,)).
    With no NaN plane in flat (plain, a bool) and a ray of finite origin and finite,
    nonzero 1 / direction, no product of the slab can be NaN, so it runs without NaN
    handling (`_slab_planes_finite`: the same values, and a cheaper loop: the NaN-aware
    one's masks were most of the walk's own time)."""
    if plain and _finite(o0, o1, o2, i0, i1, i2) and i0 != 0.0 and i1 != 0.0 and i2 != 0.0:
        for j in range(flat.shape[1]):
            ok[j], te[j], _ = _slab_planes_finite(flat[0, j], flat[1, j], flat[2, j],
                                                  flat[3, j], flat[4, j], flat[5, j], o0, o1,
                                                  o2, i0, i1, i2, tmax)
    else:
        for j in range(flat.shape[1]):
            ok[j], te[j], _ = _slab_planes(flat[0, j], flat[1, j], flat[2, j], flat[3, j],
                                           flat[4, j], flat[5, j], o0, o1, o2, i0, i1, i2,
                                           tmax)


@njit(inline="always", **JIT)
def _finite(o0, o1, o2, d0, d1, d2):
    return (np.isfinite(o0) and np.isfinite(o1) and np.isfinite(o2) and np.isfinite(d0)
            and np.isfinite(d1) and np.isfinite(d2))


@njit(inline="always", **JIT)
def _min(a, b):
    return a if a < b else b


@njit(inline="always", **JIT)
def _max(a, b):
    return a if a > b else b


@njit(inline="always", **JIT)
def _slab_by(mn, mx, lo0, lo1, lo2, hi0, hi1, hi2, o0, o1, o2, i0, i1, i2, tmax):
    """The slab arithmetic with mn / mx as the per-axis min and max."""
    t0 = (lo0 - o0) * i0
    t1 = (hi0 - o0) * i0
    t_enter, t_exit = mn(t0, t1), mx(t0, t1)
    t0 = (lo1 - o1) * i1
    t1 = (hi1 - o1) * i1
    t_enter, t_exit = mx(t_enter, mn(t0, t1)), mn(t_exit, mx(t0, t1))
    t0 = (lo2 - o2) * i2
    t1 = (hi2 - o2) * i2
    t_enter, t_exit = mx(t_enter, mn(t0, t1)), mn(t_exit, mx(t0, t1))
    # np.maximum(t_enter, 0) is NaN for a NaN t_enter, and then the ray is rejected.
    ok = (t_enter == t_enter) & (t_exit >= max(t_enter, 0.0)) & (t_enter < tmax)
    return ok, t_enter, t_exit


@njit(inline="always", **JIT)
def _node_hit(node_box, c, o0, o1, o2, i0, i1, i2, s0, s1, s2, tmax):
    """Whether some box inside node_box[c] (2, 3) may pass `_slab`; s_a = 1 where i_a < 0
    picks the near plane. Rounding of (x - o) * inv is monotone in x, so the node's slab
    interval contains each child's. Node boxes are one ulp wider than the union of their
    boxes: with a zero direction (inv = +-inf) and a box holding o on that axis, lo < o <
    hi strictly, so this axis gives (-inf, inf), never the NaN of 0 * inf."""
    t_enter = max(max((node_box[c, s0, 0] - o0) * i0, (node_box[c, s1, 1] - o1) * i1),
                  (node_box[c, s2, 2] - o2) * i2)
    t_exit = min(min((node_box[c, 1 - s0, 0] - o0) * i0, (node_box[c, 1 - s1, 1] - o1) * i1),
                 (node_box[c, 1 - s2, 2] - o2) * i2)
    return t_exit >= max(t_enter, 0.0) and t_enter < tmax


@njit(inline="always", **JIT)
def _push(node_box, first, count, stack, top, o0, o1, o2, i0, i1, i2, s0, s1, s2, tmax):
    """Push nodes first .. first + count - 1 that the ray may enter before tmax onto the
    traversal stack; returns the new top."""
    for c in range(first, first + count):
        if _node_hit(node_box, c, o0, o1, o2, i0, i1, i2, s0, s1, s2, tmax):
            stack[top] = c
            top += 1
    return top


@njit(inline="always", **JIT)
def _next_leaf(bvh, stack, top, line, tmax):
    """One step of a ray's walk through bvh = (node_box, node_child, node_start,
    node_count, prim) of `bvh_build`, for line = (o0, o1, o2, i0, i1, i2, s0, s1, s2)
    (origin, 1 / direction, s_a = i_a < 0): pop the stack down to the next leaf the ray
    may enter before tmax, pushing the children of inner nodes on the way (top -1: push
    the root first). Returns (top, lo, hi): the leaf's boxes are prim[lo:hi], and lo == hi
    once the walk is over. tmax may shrink between steps."""
    node_box, node_child, node_start, node_count, _ = bvh
    o0, o1, o2, i0, i1, i2, s0, s1, s2 = line
    if top < 0:
        top = _push(node_box, 0, 1, stack, 0, o0, o1, o2, i0, i1, i2, s0, s1, s2, tmax)
    while top > 0:
        top -= 1
        node = stack[top]
        c = node_child[node]
        if c < 0:
            return top, node_start[node], node_start[node] + node_count[node]
        top = _push(node_box, c, 2, stack, top, o0, o1, o2, i0, i1, i2, s0, s1, s2, tmax)
    return top, 0, 0


@njit(inline="always", **JIT)
def _node_enter(node_box, c, o0, o1, o2, i0, i1, i2, s0, s1, s2):
    """Where a ray enters node c's box (`nprt.workers.kernels.bvh._node_hit`'s arithmetic:
    no later than it enters any box below), or inf if it misses it."""
    t_enter = max(max((node_box[c, s0, 0] - o0) * i0, (node_box[c, s1, 1] - o1) * i1),
                  (node_box[c, s2, 2] - o2) * i2)
    t_exit = min(min((node_box[c, 1 - s0, 0] - o0) * i0, (node_box[c, 1 - s1, 1] - o1) * i1),
                 (node_box[c, 1 - s2, 2] - o2) * i2)
    return t_enter if t_exit >= max(t_enter, 0.0) else np.inf


@njit(inline="always", **JIT)
def _push_near(node_box, c, stack, stack_t, top, o0, o1, o2, i0, i1, i2, s0, s1, s2, lim):
    """Push node c with its entry distance if the ray enters it no later than lim (and
    at all: a node missed, or entered at inf, holds no box a slab test passes)."""
    t = _node_enter(node_box, c, o0, o1, o2, i0, i1, i2, s0, s1, s2)
    if t <= lim and t < np.inf:
        stack[top], stack_t[top] = c, t
        top += 1
    return top


@njit(inline="always", **JIT)
def _push_pair(node_box, c, stack, stack_t, top, o0, o1, o2, i0, i1, i2, s0, s1, s2, lim):
    """Push children c and c + 1 entered no later than lim (as `_push_near`), the nearer
    last (popped first)."""
    ta = _node_enter(node_box, c, o0, o1, o2, i0, i1, i2, s0, s1, s2)
    tb = _node_enter(node_box, c + 1, o0, o1, o2, i0, i1, i2, s0, s1, s2)
    near, far_c, t_near, t_far = c, c + 1, ta, tb
    if tb < ta:
        near, far_c, t_near, t_far = c + 1, c, tb, ta
    if t_far <= lim and t_far < np.inf:
        stack[top], stack_t[top] = far_c, t_far
        top += 1
    if t_near <= lim and t_near < np.inf:
        stack[top], stack_t[top] = near, t_near
        top += 1
    return top


def _buffers(n: int, k: int):
    """Output rows: ray (c,) int64, col (c,) int32, t_enter, t_exit (c,) float64, with
    room for four crossings per ray (scenes of overlapping boxes average about three, and
    every growth copies them all) and at least one ray's worth (k)."""
    cap = 4 * n + k + 16
    return (np.empty(cap, np.int64), np.empty(cap, np.int32), np.empty(cap), np.empty(cap))


def _grown(out, p: int):
    """The same buffers, twice as long, first p rows kept."""
    bigger = tuple(np.empty(2 * len(a), a.dtype) for a in out)
    for a, b in zip(out, bigger, strict=True):
        b[:p] = a[:p]
    return bigger


def slab_all(origin, direction, tmax, boxes):
    """Every ray against every box, ray-major, then box order.

    origin, direction : (n, 3) float64; tmax : (n,) float64; boxes : (k, 2, 3) float64
    returns ray (p,) int64, col (p,) int32 (index into boxes), t_enter, t_exit (p,) float64
    """
    out, r, p = _buffers(len(origin), len(boxes)), 0, 0
    while True:
        r, p = _all_fill(origin, direction, tmax, boxes, r, p, *out)
        if r == len(origin):
            return tuple(a[:p] for a in out)
        out = _grown(out, p)


@njit(**JIT)
def _all_fill(origin, direction, tmax, boxes, r0, p, ray, col, t_in, t_out):
    """Rays r0.. of `slab_all` into the buffers from row p, until done or a ray might not
    fit. Returns (next ray, next row). Buffers are arguments, never reassigned here:
    numba reloads arrays that a loop rebinds, which made this loop ten times slower."""
    n, k, cap = origin.shape[0], boxes.shape[0], len(ray)
    for r in range(r0, n):
        if p + k > cap:
            return r, p
        o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
        i0, i1, i2 = 1.0 / direction[r, 0], 1.0 / direction[r, 1], 1.0 / direction[r, 2]
        tm = tmax[r]
        for j in range(k):
            ok, te, tx = _slab(boxes, j, o0, o1, o2, i0, i1, i2, tm)
            if ok:
                ray[p], col[p], t_in[p], t_out[p] = r, j, te, tx
                p += 1
    return n, p


def bvh_build(boxes: np.ndarray):
    """Top-down binned SAH BVH over finite boxes (m, 2, 3) float64, m >= 1, in compiled
    code: built once per instance table (and shipped with it), O(m log m).

    returns node_box (q, 2, 3) float64 (unions of the boxes below, one ulp wider),
    node_child (q,) int32 (left child of an inner node, right = left + 1; -1 for a leaf),
    node_start, node_count (q,) int32 (a leaf's range in prim), prim (m,) int32
    """
    boxes = np.ascontiguousarray(boxes, np.float64)
    m = len(boxes)
    if boxes.shape != (m, 2, 3) or m == 0:
        raise ValueError(f"bvh_build: boxes must have shape (m >= 1, 2, 3), got {boxes.shape}")
    node_box, node_child, node_start, node_count, prim, q = _bvh_build(boxes)
    node_box = np.stack([np.nextafter(node_box[:q, 0], -np.inf),
                         np.nextafter(node_box[:q, 1], np.inf)], axis=1)
    return node_box, node_child[:q], node_start[:q], node_count[:q], prim


# Centroid bins per axis in the SAH sweep: more bins approach the full sweep's trees,
# fewer build faster; 16 is the usual choice (Wald 2007).
BVH_BINS = 16


@njit(**JIT)
def _bvh_build(boxes):
    """`bvh_build` before the node boxes are widened; also returns the node count q.
    A node whose centroids all coincide (no bin split exists) is halved by position."""
    m = boxes.shape[0]
    cap = 2 * m - 1
    node_box = np.empty((cap, 2, 3))
    node_child = np.full(cap, -1, np.int32)
    node_start = np.zeros(cap, np.int32)
    node_count = np.zeros(cap, np.int32)
    prim = np.arange(m).astype(np.int32)
    centre = np.empty((m, 3))
    for i in range(m):
        for a in range(3):
            centre[i, a] = 0.5 * boxes[i, 0, a] + 0.5 * boxes[i, 1, a]  # never overflows
    c_lo, c_hi = np.empty(3), np.empty(3)  # centroid bounds of the node
    sweep = _SweepScratch(np.empty((BVH_BINS, 3)), np.empty((BVH_BINS, 3)),
                          np.zeros(BVH_BINS, np.int64), np.empty(BVH_BINS), np.empty(3),
                          np.empty(3), np.empty(3), np.empty(3))
    right = np.empty(m, np.int32)  # right-hand prims of the node being split
    stack = np.empty((cap, 3), np.int64)  # (node, start, end) still to build
    stack[0, 0], stack[0, 1], stack[0, 2] = 0, 0, m
    top, q = 1, 1
    while top > 0:
        top -= 1
        node, s, e = stack[top, 0], stack[top, 1], stack[top, 2]
        _node_bounds(boxes, centre, prim, s, e, node_box[node], c_lo, c_hi)
        node_start[node], node_count[node] = s, e - s
        if e - s <= BVH_LEAF_SIZE:
            continue
        best_axis, best_bin = _best_split(boxes, centre, prim, s, e, c_lo, c_hi, sweep)
        if best_axis < 0:
            mid = s + (e - s) // 2
        else:
            mid = _partition(centre, prim, s, e, best_axis, best_bin, c_lo[best_axis],
                             c_hi[best_axis] - c_lo[best_axis], right)
        node_child[node] = q
        stack[top, 0], stack[top, 1], stack[top, 2] = q, s, mid
        stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2] = q + 1, mid, e
        top += 2
        q += 2
    return node_box, node_child, node_start, node_count, prim, q


_SweepScratch = namedtuple("_SweepScratch", "bin_lo bin_hi bin_n right_area r_lo r_hi l_lo l_hi")


@njit(inline="always", **JIT)
def _node_bounds(boxes, centre, prim, s, e, box, c_lo, c_hi):
    """box (2, 3) = the union of boxes prim[s:e]; c_lo, c_hi (3,) their centroids' bounds."""
    c_lo[:] = np.inf
    c_hi[:] = -np.inf
    for a in range(3):
        lo, hi = np.inf, -np.inf
        for x in range(s, e):
            b = prim[x]
            lo = min(lo, boxes[b, 0, a])
            hi = max(hi, boxes[b, 1, a])
            c_lo[a] = min(c_lo[a], centre[b, a])
            c_hi[a] = max(c_hi[a], centre[b, a])
        box[0, a], box[1, a] = lo, hi


@njit(inline="always", **JIT)
def _best_split(boxes, centre, prim, s, e, c_lo, c_hi, w):
    """The binned SAH split of prim[s:e]: (axis, last bin of the left side), or (-1, -1)
    when no axis has two non-empty sides. w: a `_SweepScratch`."""
    best_cost, best_axis, best_bin = np.inf, -1, -1
    for a in range(3):
        ext = c_hi[a] - c_lo[a]
        if not ext > 0.0:
            continue
        w.bin_n[:] = 0
        w.bin_lo[:] = np.inf
        w.bin_hi[:] = -np.inf
        for x in range(s, e):
            b = prim[x]
            k = _bin(centre[b, a], c_lo[a], ext)
            w.bin_n[k] += 1
            for y in range(3):
                w.bin_lo[k, y] = min(w.bin_lo[k, y], boxes[b, 0, y])
                w.bin_hi[k, y] = max(w.bin_hi[k, y], boxes[b, 1, y])
        # Sweep from the right: right_area[k] is the half area of bins k..end.
        w.r_lo[:] = np.inf
        w.r_hi[:] = -np.inf
        for k in range(BVH_BINS - 1, 0, -1):
            for y in range(3):
                w.r_lo[y] = min(w.r_lo[y], w.bin_lo[k, y])
                w.r_hi[y] = max(w.r_hi[y], w.bin_hi[k, y])
            w.right_area[k] = _half_area3(w.r_lo, w.r_hi)
        w.l_lo[:] = np.inf
        w.l_hi[:] = -np.inf
        n_left = 0
        for k in range(BVH_BINS - 1):  # split between bins k and k + 1
            n_left += w.bin_n[k]
            for y in range(3):
                w.l_lo[y] = min(w.l_lo[y], w.bin_lo[k, y])
                w.l_hi[y] = max(w.l_hi[y], w.bin_hi[k, y])
            n_right = (e - s) - n_left
            if n_left == 0 or n_right == 0:
                continue
            cost = _half_area3(w.l_lo, w.l_hi) * n_left + w.right_area[k + 1] * n_right
            if cost < best_cost:
                best_cost, best_axis, best_bin = cost, a, k
    return best_axis, best_bin


@njit(inline="always", **JIT)
def _partition(centre, prim, s, e, axis, last_bin, lo, ext, right):
    """Stable partition of prim[s:e] by centroid bin (<= last_bin left): left prims are
    compacted in place, right ones buffered in `right` and appended. Returns the middle."""
    i, j = s, 0
    for x in range(s, e):
        b = prim[x]
        if _bin(centre[b, axis], lo, ext) <= last_bin:
            prim[i] = b
            i += 1
        else:
            right[j] = b
            j += 1
    prim[i:e] = right[:j]
    return i


@njit(inline="always", **JIT)
def _bin(c, lo, ext):
    """The bin of centroid coordinate c in [lo, lo + ext], ext > 0: divided, not scaled
    by BVH_BINS / ext, which is inf for a subnormal ext. An ext of inf (an overflowed
    difference) puts every centroid in bin 0 (or NaN: bin 0 too), so no split is taken."""
    f = (c - lo) / ext * BVH_BINS
    return min(np.int64(f), BVH_BINS - 1) if f > 0.0 else 0


@njit(inline="always", **JIT)
def _half_area3(lo, hi):
    """Half the surface area of the box lo, hi (3,) float64."""
    x, y, z = hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]
    return x * y + y * z + z * x


def bvh_slab(origin, direction, tmax, boxes, node_box, node_child, node_start, node_count,
             prim, col_of):
    """`slab_all` over the boxes whose col_of (m,) int32 is >= 0 (their position in the
    requested instance list, unique), through the BVH from `bvh_build(boxes)`. Shapes
    and dtypes as in `slab_all`; crossings come out ray-major, then by col."""
    k = int(col_of.max()) + 1
    members = np.full(k, -1, np.int64)  # col -> box
    members[col_of[col_of >= 0]] = np.flatnonzero(col_of >= 0)
    scratch = (np.empty(k, np.int32), np.empty(k), np.empty(k),  # one ray's crossings
               np.empty(len(node_child) + 1, np.int32))  # traversal stack
    out, r, p = _buffers(len(origin), k), 0, 0
    while True:
        r, p = _bvh_fill(origin, direction, tmax, boxes, node_box, node_child, node_start,
                         node_count, prim, col_of, members, r, p, *out, *scratch)
        if r == len(origin):
            return tuple(a[:p] for a in out)
        out = _grown(out, p)


@njit(**JIT)
def _bvh_fill(origin, direction, tmax, boxes, node_box, node_child, node_start, node_count,
              prim, col_of, members, r0, p, ray, col, t_in, t_out, hit_col, hit_in, hit_out,
              stack):
    """Rays r0.. of `bvh_slab`, as `_all_fill`. Rays with a non-finite origin or direction
    component take the plain loop: the node test does not mirror the reference formula's
    NaN cases for them."""
    n, k, cap = origin.shape[0], members.shape[0], len(ray)
    bvh = (node_box, node_child, node_start, node_count, prim)
    for r in range(r0, n):
        if p + k > cap:
            return r, p
        o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
        d0, d1, d2 = direction[r, 0], direction[r, 1], direction[r, 2]
        i0, i1, i2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
        s0, s1, s2 = int(i0 < 0.0), int(i1 < 0.0), int(i2 < 0.0)
        tm = tmax[r]
        h = 0
        if (np.isfinite(o0) and np.isfinite(o1) and np.isfinite(o2) and np.isfinite(d0)
                and np.isfinite(d1) and np.isfinite(d2)):
            line = (o0, o1, o2, i0, i1, i2, s0, s1, s2)
            top, lo, hi = _next_leaf(bvh, stack, -1, line, tm)
            while lo < hi:
                for x in range(lo, hi):
                    b = prim[x]
                    j = col_of[b]
                    if j < 0:
                        continue
                    ok, te, tx = _slab(boxes, b, o0, o1, o2, i0, i1, i2, tm)
                    if ok:  # insert by col: a ray crosses few boxes
                        y = h
                        while y > 0 and hit_col[y - 1] > j:
                            hit_col[y], hit_in[y], hit_out[y] = (
                                hit_col[y - 1], hit_in[y - 1], hit_out[y - 1])
                            y -= 1
                        hit_col[y], hit_in[y], hit_out[y] = j, te, tx
                        h += 1
                top, lo, hi = _next_leaf(bvh, stack, top, line, tm)
        else:
            for j in range(k):
                ok, te, tx = _slab(boxes, members[j], o0, o1, o2, i0, i1, i2, tm)
                if ok:
                    hit_col[h], hit_in[h], hit_out[h] = j, te, tx
                    h += 1
        for y in range(h):
            ray[p], col[p], t_in[p], t_out[p] = r, hit_col[y], hit_in[y], hit_out[y]
            p += 1
    return n, p
