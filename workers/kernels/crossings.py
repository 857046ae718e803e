"""Jitted kernels that trace each ray's instance boxes through Embree's C API, nearest box
first, in one compiled loop: Embree's functions are called by address (passed in from
`nprt.workers.traversal.rtc`, which opens the library and builds the scenes), so nothing
here depends on the process and numba caches these kernels like the others."""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from nprt.workers.kernels.pairs import _to_local_row

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


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


@njit(inline="always", **JIT)
def closest1(fn, scene, rh, ri, o0, o1, o2, d0, d1, d2, tfar):
    """Embree's closest hit of one ray (tnear 0) in scene, through fn = INTERSECT1: rh the
    `rayhit_buffer_nb`, ri its uint32 view. Returns (t, prim (-1: none), u, v)."""
    rh[0], rh[1], rh[2], rh[3] = o0, o1, o2, np.float32(0.0)
    rh[4], rh[5], rh[6], rh[7] = d0, d1, d2, np.float32(0.0)
    rh[8] = tfar
    ri[9], ri[10], ri[11] = RTC_INVALID_ID, 0, 0
    ri[17], ri[18], ri[19] = RTC_INVALID_ID, RTC_INVALID_ID, RTC_INVALID_ID
    _call3(fn, np.uint64(scene), np.uint64(rh.ctypes.data), np.uint64(0))
    if ri[18] == RTC_INVALID_ID:
        return rh[8], np.int32(-1), rh[15], rh[16]
    return rh[8], np.int32(ri[17]), rh[15], rh[16]


@njit(inline="always", **JIT)
def occluded1_ray(fn, scene, rh, ri, o0, o1, o2, d0, d1, d2, tfar):
    """Whether scene blocks the segment (0, tfar) of one ray (as embreex's OCCLUDED),
    through fn = OCCLUDED1."""
    rh[0], rh[1], rh[2], rh[3] = o0, o1, o2, np.float32(0.0)
    rh[4], rh[5], rh[6], rh[7] = d0, d1, d2, np.float32(0.0)
    rh[8] = tfar
    ri[9], ri[10], ri[11] = RTC_INVALID_ID, 0, 0
    _call3(fn, np.uint64(scene), np.uint64(rh.ctypes.data), np.uint64(0))
    return not rh[8] >= 0.0  # Embree sets tfar to -inf on a hit


@njit(**JIT)
def closest_crossings(fn, ray, inst, rank, t_enter, box_slack, tmax, far, mesh_of, scene_of_mesh,
                      world_to_local, origin, direction, best_t, best_inst, best_prim, best_u,
                      best_v):
    """Each ray's crossings (ray-major, rank from `entry_rank`) traced nearest box first,
    stopping at the first box entered beyond its closest hit so far (or tmax) stretched by
    box_slack; Embree gets tfar = far. Hits fold in place into best_* (n,) (best_inst -1:
    none yet): a hit at t <= tmax wins on a smaller t, and on equal t the lower instance,
    so any shard split agrees. origin, direction (n, 3) float64; scene_of_mesh (M,)
    uint64."""
    rh, ri, lo, ld, order = _scratch()
    a = 0
    while a < ray.shape[0]:
        b, order = _ray_run(ray, rank, a, order)
        r = ray[a]
        cut = np.float64(tmax[r])
        for k in range(b - a):
            x = order[k]
            if not t_enter[x] <= cut * (1.0 + box_slack):
                break
            i = inst[x]
            _to_local_row(world_to_local, i, origin, direction, r, lo, ld, 0)
            t, prim, u, v = closest1(fn, scene_of_mesh[mesh_of[i]], rh, ri, lo[0, 0], lo[0, 1],
                                     lo[0, 2], ld[0, 0], ld[0, 1], ld[0, 2], far)
            if prim < 0 or not t <= tmax[r]:
                continue
            if best_inst[r] < 0 or t < best_t[r] or (t == best_t[r] and i < best_inst[r]):
                best_t[r], best_inst[r], best_prim[r] = t, i, prim
                best_u[r], best_v[r] = u, v
                if t < cut:
                    cut = np.float64(t)
        a = b


@njit(**JIT)
def occluded_crossings(fn, ray, inst, rank, tmax, mesh_of, scene_of_mesh, world_to_local, origin,
                       direction, occluded):
    """occluded[r] = some crossing of ray r (ray-major, traced nearest box first) blocks
    (0, tmax[r]); a ray stops at its first occluder."""
    rh, ri, lo, ld, order = _scratch()
    a = 0
    while a < ray.shape[0]:
        b, order = _ray_run(ray, rank, a, order)
        r = ray[a]
        for k in range(b - a):
            i = inst[order[k]]
            _to_local_row(world_to_local, i, origin, direction, r, lo, ld, 0)
            if occluded1_ray(fn, scene_of_mesh[mesh_of[i]], rh, ri, lo[0, 0], lo[0, 1], lo[0, 2],
                             ld[0, 0], ld[0, 1], ld[0, 2], tmax[r]):
                occluded[r] = True
                break
        a = b


@njit(inline="always", **JIT)
def _scratch():
    """One ray's buffers: the RTCRayHit (as float32 and uint32 views), its local origin and
    direction (1, 3) float32, and the rank-to-crossing order of its crossings."""
    rh = rayhit_buffer_nb()
    return (rh, rh.view(np.uint32), np.empty((1, 3), np.float32),
            np.empty((1, 3), np.float32), np.empty(64, np.int64))


@njit(inline="always", **JIT)
def _ray_run(ray, rank, a, order):
    """The crossings of ray[a] run from a to the returned b; order[k] (grown if needed) is
    the one of rank k."""
    b = a + 1
    while b < ray.shape[0] and ray[b] == ray[a]:
        b += 1
    if b - a > order.shape[0]:
        order = np.empty(2 * (b - a), np.int64)
    for x in range(a, b):
        order[rank[x]] = x
    return b, order


@njit(inline="always", **JIT)
def rayhit_buffer_nb():
    """`rayhit_buffer` inside compiled code."""
    raw = np.zeros(RAYHIT_FLOATS + 4, np.float32)
    skip = ((16 - raw.ctypes.data % 16) % 16) // 4
    return raw[skip:skip + RAYHIT_FLOATS]
