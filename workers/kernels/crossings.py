"""Jitted kernels that walk each ray through the top level (the instance boxes, through
their BVH) and trace the boxes it reaches through Embree's C API, in one compiled loop a
ray: no list of crossings is written or sorted. Embree's functions are called by address
(passed in from `nprt.workers.traversal.rtc`, which opens the library and builds the
scenes), so nothing here depends on the process and numba caches these kernels like the
others."""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from nprt.workers.kernels.bvh import (
    _finite,
    _flat_slabs,
    _next_leaf,
    _push_near,
    _push_pair,
    _slab,
)
from nprt.workers.kernels.nearest import near_search
from nprt.workers.kernels.pairs import to_local_ray
from nprt.workers.traversal.planar import DIR_MAX, DIR_MIN, GAP_MIN

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
# The loops over rays allocate nothing, so they run without reference counting.
JIT_RAW = {**JIT, "_nrt": False}


@intrinsic
def _call3(typingctx, fn, a, b, c):
    """Call the C function at address fn (uint64) as void f(uint64, uint64, uint64)."""
    sig = types.void(types.uint64, types.uint64, types.uint64, types.uint64)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(ir.VoidType(), [i64, i64, i64])
        ptr = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(ptr, list(args[1:]))
        return context.get_dummy_value()

    return sig, codegen


RTC_INVALID_ID = 0xFFFFFFFF
# RTCRayHit as floats (uint32 fields through a view): ray org 0-2, tnear 3, dir 4-6,
# time 7, tfar 8, mask 9, id 10, flags 11; hit Ng 12-14, u 15, v 16, primID 17,
# geomID 18, instID 19. 16-byte aligned; 32 floats leave room for any instance levels.
RAYHIT_FLOATS = 32
# Embree traces a box with tfar = the closest hit so far (or tmax) stretched by this much
# (8192 float32 ulps); see `_closest_box` for why the hit it reports is then the one it
# reports with no limit.
TFAR_MARGIN_REL = 2.0**-10
# Below this (0, subnormal, negative), a stretch is no margin: Embree gets far.
TFAR_MIN = 1e-30


@njit(inline="always", **JIT)
def closest1(fn, scene, ptr, rh, ri, o0, o1, o2, d0, d1, d2, tfar):
    """Embree's closest hit of one ray (tnear 0) in scene, through fn = INTERSECT1: rh the
    `rayhit_buffer_nb` at address ptr (uint64), ri its uint32 view. Returns (t, prim (-1:
    none), u, v)."""
    rh[0], rh[1], rh[2], rh[3] = o0, o1, o2, np.float32(0.0)
    rh[4], rh[5], rh[6], rh[7] = d0, d1, d2, np.float32(0.0)
    rh[8] = tfar
    ri[9], ri[10], ri[11] = RTC_INVALID_ID, 0, 0
    ri[17], ri[18], ri[19] = RTC_INVALID_ID, RTC_INVALID_ID, RTC_INVALID_ID
    _call3(fn, np.uint64(scene), ptr, np.uint64(0))
    if ri[18] == RTC_INVALID_ID:
        return rh[8], np.int32(-1), rh[15], rh[16]
    return rh[8], np.int32(ri[17]), rh[15], rh[16]


@njit(inline="always", **JIT)
def occluded1_ray(fn, scene, ptr, rh, ri, o0, o1, o2, d0, d1, d2, tfar):
    """Whether scene blocks the segment (0, tfar) of one ray (as embreex's OCCLUDED),
    through fn = OCCLUDED1; buffers as `closest1`."""
    rh[0], rh[1], rh[2], rh[3] = o0, o1, o2, np.float32(0.0)
    rh[4], rh[5], rh[6], rh[7] = d0, d1, d2, np.float32(0.0)
    rh[8] = tfar
    ri[9], ri[10], ri[11] = RTC_INVALID_ID, 0, 0
    _call3(fn, np.uint64(scene), ptr, np.uint64(0))
    return not rh[8] >= 0.0  # Embree sets tfar to -inf on a hit


@njit(**JIT)
def closest_walk(fn, origin, direction, tmax, box_slack, far, boxes, members, col_of, use_bvh,
                 flat, node_box, node_child, node_start, node_count, prim, mesh_of,
                 scene_of_mesh, planes, world_to_local, best_t, best_inst, best_prim, best_u,
                 best_v, route, cand_owner, cands, cand_flat, cand_bvh, visited, near_t, near_owner,
                 near_tmax):
    """Each ray's closest hit among the instance boxes `members` (k,) int64 (indices into
    boxes (m, 2, 3) float64; col_of (m,) int32 >= 0 for members), in one loop a ray: the
    boxes it crosses before tmax stretched by box_slack (through the top-level BVH when
    use_bvh, else all members' slabs in one flat loop; flat (6, k) float64 their boxes
    as rows lo x, y, z, hi x, y, z) are gathered nearest entry first, then traced
    through Embree until the next is entered beyond the closest hit so far (stretched
    alike): no hit there can win or tie. Embree's tfar is far, or the closest hit so far
    stretched by TFAR_MARGIN_REL (the same hits: see `_closest_box`). Hits fold into
    best_* (n,) (best_inst -1: none yet): a hit at t <= tmax wins on a smaller t, on
    equal t the lower instance, so the answer depends neither on the order boxes are
    traced in nor on how instances are split over shards. origin, direction (n, 3)
    float64, tmax (n,) float32. planes (M, 3) float64 (`nprt.workers.traversal.planar.
    plane_rows`): a box whose mesh lies in a plane the local ray leaves is not traced,
    Embree would find nothing there.

    With route, each ray then also gets the exact policy's next stop (`near_search`):
    near_t (n,) float64 and near_owner (n,) int32, the nearest entry and its owner of a
    candidate box (cands, cand_owner, cand_flat, cand_bvh: see `near_search`) on a
    shard not in visited (n,) uint64, crossed before near_tmax (n,) float32 (the final
    cut, the closest hit here or tmax) stretched by box_slack. The caller cuts it again
    at the final tmax, no larger than near_tmax (`nprt.workers.routing.exact.next_stop`).
    The search runs after the tracing (a second loop of this kernel over the rays),
    culled at that cut and at its best so far: taking
    the candidates in the gather instead (one pass, bounded by the incoming tmax only, so
    every slab before it, often the whole scene's depth) cost the local walk as much as
    the separate search saved (in process, forest and city K = 4 and 8).
    """
    rh, ri, ptr = _scratch()
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    q_t, q_id = np.empty(boxes.shape[0] + 1), np.empty(boxes.shape[0] + 1, np.int64)
    f_te, f_ok = np.empty(flat.shape[1]), np.empty(flat.shape[1], np.bool_)
    _closest_rays(fn, origin, direction, tmax, box_slack, far, boxes, members, col_of, use_bvh,
                  flat, node_box, node_child, node_start, node_count, prim, mesh_of,
                  scene_of_mesh, planes, world_to_local, best_t, best_inst, best_prim, best_u,
                  best_v, route, near_tmax, rh, ri, ptr, stack, q_t, q_id, f_te, f_ok,
                  not np.isnan(flat).any())
    if route:
        bvh = (node_box, node_child, node_start, node_count, prim)
        near_search(origin, direction, near_tmax.astype(np.float64) * (1.0 + box_slack),
                    np.ones(origin.shape[0], np.bool_), boxes, bvh, cand_owner, cands,
                    cand_flat, cand_bvh, visited, near_t, near_owner)


@njit(**JIT_RAW)
def _closest_rays(fn, origin, direction, tmax, box_slack, far, boxes, members, col_of, use_bvh,
                  flat, node_box, node_child, node_start, node_count, prim, mesh_of,
                  scene_of_mesh, planes, world_to_local, best_t, best_inst, best_prim, best_u,
                  best_v, route, near_tmax, rh, ri, ptr, stack, q_t, q_id, f_te, f_ok, plain):
    """`closest_walk`'s loop over the rays, on scratch the caller made (rh, ri, ptr from
    `_scratch`; stack, q_t, q_id, f_te, f_ok sized as there). Compiled without numba's
    reference counting, which it does not need (it allocates nothing): with it, every
    inlined helper took and dropped a reference to each array it was handed, a locked
    increment and decrement each, at every box (a quarter of the walk's samples under
    perf, sculpture closest hits). plain: flat holds no NaN (`_flat_queue`)."""
    bvh = (node_box, node_child, node_start, node_count, prim)
    for r in range(origin.shape[0]):
        o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
        d0, d1, d2 = direction[r, 0], direction[r, 1], direction[r, 2]
        i0, i1, i2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
        box_tmax = np.float64(tmax[r]) * (1.0 + box_slack)
        h = 0
        if use_bvh and _finite(o0, o1, o2, d0, d1, d2):
            s0, s1, s2 = int(i0 < 0.0), int(i1 < 0.0), int(i2 < 0.0)
            line = (o0, o1, o2, i0, i1, i2, s0, s1, s2)
            top, lo, hi = _next_leaf(bvh, stack, -1, line, box_tmax)
            while lo < hi:
                for x in range(lo, hi):
                    b = prim[x]
                    if col_of[b] >= 0:
                        ok, te, _ = _slab(boxes, b, o0, o1, o2, i0, i1, i2, box_tmax)
                        if ok:
                            h = _enqueue(q_t, q_id, h, te, b)
                top, lo, hi = _next_leaf(bvh, stack, top, line, box_tmax)
        else:  # few boxes, or a ray the node test does not cover: every member's slab
            h = _flat_queue(flat, plain, members, o0, o1, o2, i0, i1, i2, box_tmax, f_te, f_ok, q_t,
                            q_id)
        cut = np.float64(tmax[r])
        while h > 0:
            h -= 1
            if not q_t[h] <= cut * (1.0 + box_slack):
                break  # everything left is entered beyond the closest hit
            cut = _closest_box(fn, q_id[h], r, cut, far, tmax, mesh_of, scene_of_mesh, planes,
                               world_to_local, origin, direction, ptr, rh, ri, best_t,
                               best_inst, best_prim, best_u, best_v)
        if route:
            near_tmax[r] = np.float32(cut)  # a float32 t or tmax: exact


@njit(inline="always", **JIT)
def _enqueue(q_t, q_id, h, t, x):
    """Insert box x entered at t into the queue q_t, q_id of h entries kept farthest first
    (the nearest pops from the end). Returns the new length."""
    y = h
    while y > 0 and q_t[y - 1] < t:
        q_t[y], q_id[y] = q_t[y - 1], q_id[y - 1]
        y -= 1
    q_t[y], q_id[y] = t, x
    return h + 1


@njit(inline="always", **JIT)
def _flat_queue(flat, plain, members, o0, o1, o2, i0, i1, i2, tmax, te, ok, q_t, q_id):
    """Queue (`_enqueue`) every member box the ray crosses before tmax (`_flat_slabs`).
    Returns the queue's length."""
    _flat_slabs(flat, plain, o0, o1, o2, i0, i1, i2, tmax, te, ok)
    h = 0
    for j in range(flat.shape[1]):
        if ok[j]:
            h = _enqueue(q_t, q_id, h, te[j], members[j])
    return h


@njit(inline="always", **JIT)
def _closest_box(fn, b, r, cut, far, tmax, mesh_of, scene_of_mesh, planes, world_to_local,
                 origin, direction, ptr, rh, ri, best_t, best_inst, best_prim, best_u, best_v):
    """Trace ray r in instance b and fold its hit into best_*. Returns the new cut (the
    closest hit's t so far, or tmax) as float64.

    Only a hit at t <= cut can change best_*, and Embree, given tfar = C > cut by a wide
    margin instead of far, reports the same hit there: its traversal visits nodes in an
    order set by their entry distances alone, culls a node entered beyond tfar, and
    accepts the nearest triangle of a leaf at t <= tfar, then lowers tfar to it. A run
    from C visits the nodes of a run from far, less ones entered beyond C (whose hits
    all lie beyond cut), and accepts the same hits up to C; so its last accepted hit at
    or before cut, the answer, is the same triangle, u and v."""
    o0, o1, o2, d0, d1, d2 = to_local_ray(world_to_local, b, origin, direction, r)
    m = mesh_of[b]
    if _leaves_plane(planes, m, o0, o1, o2, d0, d1, d2):
        return cut  # Embree finds no hit there (`nprt.workers.traversal.planar`)
    tfar = far
    if TFAR_MIN < cut and cut * (1.0 + TFAR_MARGIN_REL) < far:
        tfar = np.float32(cut * (1.0 + TFAR_MARGIN_REL))
    t, p, u, v = closest1(fn, scene_of_mesh[m], ptr, rh, ri, o0, o1, o2, d0, d1, d2,
                          tfar)
    if p < 0 or not t <= tmax[r]:
        return cut
    if best_inst[r] < 0 or t < best_t[r] or (t == best_t[r] and b < best_inst[r]):
        best_t[r], best_inst[r], best_prim[r] = t, b, p
        best_u[r], best_v[r] = u, v
        if t < cut:
            return np.float64(t)
    return cut


@njit(**JIT)
def occluded_walk(fn, origin, direction, tmax, box_slack, boxes, members, col_of, use_bvh, flat,
                  node_box, node_child, node_start, node_count, prim, mesh_of, scene_of_mesh,
                  planes, world_to_local, occluded, route, cand_owner, cands, cand_flat, cand_bvh,
                  visited, near_t, near_owner):
    """occluded[r] = some box of `members` crossed before tmax[r] holds a triangle on
    (0, tmax[r]); a ray stops at its first occluder. Any order of trying the boxes gives
    the same answer, so they are tried in the BVH's order or the flat loop's (members'),
    with no queue. Arrays as `closest_walk`; with route, a ray not occluded here also gets the exact
    policy's next stop before tmax stretched by box_slack (a shadow ray keeps its tmax),
    as `closest_walk`'s (near_* of an occluded ray mean nothing: it ends here)."""
    rh, ri, ptr = _scratch()
    stack, stack_t = np.empty(node_child.shape[0] + 1, np.int32), np.empty(node_child.shape[0] + 1)
    f_te, f_ok = np.empty(flat.shape[1]), np.empty(flat.shape[1], np.bool_)
    _occluded_rays(fn, origin, direction, tmax, boxes, members, col_of, use_bvh, flat, node_box,
                   node_child, node_start, node_count, prim, mesh_of, scene_of_mesh, planes,
                   world_to_local, occluded, rh, ri, ptr, stack, stack_t, f_te, f_ok,
                   not np.isnan(flat).any())
    if route:
        bvh = (node_box, node_child, node_start, node_count, prim)
        near_search(origin, direction, tmax.astype(np.float64) * (1.0 + box_slack), ~occluded,
                    boxes, bvh, cand_owner, cands, cand_flat, cand_bvh, visited, near_t,
                    near_owner)


@njit(**JIT_RAW)
def _occluded_rays(fn, origin, direction, tmax, boxes, members, col_of, use_bvh, flat, node_box,
                   node_child, node_start, node_count, prim, mesh_of, scene_of_mesh, planes,
                   world_to_local, occluded, rh, ri, ptr, stack, stack_t, f_te, f_ok, plain):
    """`occluded_walk`'s loop over the rays, on the caller's scratch, without reference
    counting (as `_closest_rays`)."""
    for r in range(origin.shape[0]):
        o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
        d0, d1, d2 = direction[r, 0], direction[r, 1], direction[r, 2]
        i0, i1, i2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
        tm = np.float64(tmax[r])
        if use_bvh and _finite(o0, o1, o2, d0, d1, d2):
            s0, s1, s2 = int(i0 < 0.0), int(i1 < 0.0), int(i2 < 0.0)
            top = _push_near(node_box, 0, stack, stack_t, 0, o0, o1, o2, i0, i1, i2, s0, s1,
                             s2, tm)
            while top > 0 and not occluded[r]:
                top -= 1
                node = stack[top]
                c = node_child[node]
                if c >= 0:
                    top = _push_pair(node_box, c, stack, stack_t, top, o0, o1, o2, i0, i1, i2,
                                     s0, s1, s2, tm)
                    continue
                for x in range(node_start[node], node_start[node] + node_count[node]):
                    b = prim[x]
                    if col_of[b] >= 0 and _occluded_box(fn, b, r, boxes, o0, o1, o2, i0, i1,
                                                        i2, tmax, mesh_of, scene_of_mesh, planes,
                                                        world_to_local, origin, direction,
                                                        ptr, rh, ri):
                        occluded[r] = True
                        break
        else:  # any order gives the same answer: the crossed boxes in member order
            _flat_slabs(flat, plain, o0, o1, o2, i0, i1, i2, tm, f_te, f_ok)
            for j in range(flat.shape[1]):
                if f_ok[j] and _occluded_in(fn, members[j], r, tmax, mesh_of, scene_of_mesh,
                                            planes, world_to_local, origin, direction, ptr,
                                            rh, ri):
                    occluded[r] = True
                    break


@njit(inline="always", **JIT)
def _occluded_box(fn, b, r, boxes, o0, o1, o2, i0, i1, i2, tmax, mesh_of, scene_of_mesh, planes,
                  world_to_local, origin, direction, ptr, rh, ri):
    """Whether ray r crosses instance b's box before tmax[r] and a triangle there blocks
    (0, tmax[r])."""
    ok, _, _ = _slab(boxes, b, o0, o1, o2, i0, i1, i2, np.float64(tmax[r]))
    return ok and _occluded_in(fn, b, r, tmax, mesh_of, scene_of_mesh, planes, world_to_local,
                               origin, direction, ptr, rh, ri)


@njit(inline="always", **JIT)
def _occluded_in(fn, b, r, tmax, mesh_of, scene_of_mesh, planes, world_to_local, origin,
                 direction, ptr, rh, ri):
    """Whether a triangle of instance b blocks (0, tmax[r]) of ray r."""
    l0, l1, l2, e0, e1, e2 = to_local_ray(world_to_local, b, origin, direction, r)
    m = mesh_of[b]
    if _leaves_plane(planes, m, l0, l1, l2, e0, e1, e2):
        return False  # Embree finds no hit there (`nprt.workers.traversal.planar`)
    return occluded1_ray(fn, scene_of_mesh[m], ptr, rh, ri, l0, l1, l2, e0, e1, e2, tmax[r])


@njit(inline="always", **JIT)
def _leaves_plane(planes, m, o0, o1, o2, d0, d1, d2):
    """Whether mesh m lies in a plane of its local axes that the local ray o, d (float32
    scalars, as Embree gets them) leaves, within the bounds under which Embree's robust
    test rejects every triangle of it (`nprt.workers.traversal.planar`). planes (M, 3)
    float64: per mesh axis (-1: not planar), the plane's coordinate c, reach."""
    a = planes[m, 0]
    if a < 0.0:
        return False
    reach = planes[m, 2]
    if not (abs(o0) <= reach and abs(o1) <= reach and abs(o2) <= reach
            and abs(d0) <= DIR_MAX and abs(d1) <= DIR_MAX and abs(d2) <= DIR_MAX):
        return False  # also any NaN
    oa, da = o0, d0
    if a == 1.0:
        oa, da = o1, d1
    elif a == 2.0:
        oa, da = o2, d2
    gap = planes[m, 1] - np.float64(oa)  # c - O_a
    return (gap < -GAP_MIN and da > DIR_MIN) or (gap > GAP_MIN and da < -DIR_MIN)


@njit(inline="always", **JIT)
def _scratch():
    """One ray's RTCRayHit: as float32 and uint32 views, and its address (uint64)."""
    rh = rayhit_buffer_nb()
    return rh, rh.view(np.uint32), np.uint64(rh.ctypes.data)


@njit(inline="always", **JIT)
def rayhit_buffer_nb():
    """`rayhit_buffer` inside compiled code."""
    raw = np.zeros(RAYHIT_FLOATS + 4, np.float32)
    skip = ((16 - raw.ctypes.data % 16) % 16) // 4
    return raw[skip:skip + RAYHIT_FLOATS]
