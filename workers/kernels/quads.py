"""Jitted quad-light intersection and camera rays, with the float operations of the numpy
formulas they replace (`LightSet.intersect_quads`, `generate_primary` until now).

Those formulas took three-term dot products as `(n, 3) @ (3,)` float64 products, which
numpy hands to BLAS (OpenBLAS's dgemv): its rounding is that of two fused multiply-adds,
fma(a2, b2, fma(a0, b0, a1 b1)) (`dot3`), for any row count (checked against numpy in
tests/workers/test_quads.py). Here that order is written out, so the answer no longer
depends on which BLAS kernel a machine picks.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from nprt.workers.kernels.rng import CAMERA_BOUNCE, dim_key, uniform_keyed

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c rounded once (llvm.fma.f64), for float64 a, b, c."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        f64 = ir.DoubleType()
        fn = builder.module.globals.get("llvm.fma.f64")
        if fn is None:
            fn = ir.Function(builder.module, ir.FunctionType(f64, [f64, f64, f64]),
                             "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


@njit(inline="always", **JIT)
def dot3(a0, a1, a2, b0, b1, b2):
    """The three-term dot product as numpy's float64 `(n, 3) @ (3,)` rounds it."""
    return fma(a2, b2, fma(a0, b0, a1 * b1))


@njit(**JIT)
def intersect_quads(origin, direction, tmax, corner, normal, edge_u, edge_v, uu, vv):
    """Each ray's closest quad hit from the emitting side within (0, tmax], t compared as
    float32; on equal t the lower light. origin (n, 3) float64, direction (n, 3) float32,
    tmax (n,) float32; corner, normal, edge_u, edge_v (L, 3) float64; uu, vv (L,) float64
    the squared edge lengths (as numpy's `u @ u`). Returns t (n,) float32 (inf: none) and
    light (n,) int32 (-1: none)."""
    n = origin.shape[0]
    best_t = np.full(n, np.inf, np.float32)
    best_l = np.full(n, -1, np.int32)
    for r in range(n):
        o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
        d0, d1, d2 = (np.float64(direction[r, 0]), np.float64(direction[r, 1]),
                      np.float64(direction[r, 2]))
        for i in range(corner.shape[0]):
            n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
            denom = dot3(d0, d1, d2, n0, n1, n2)  # < 0 when arriving at the emitting face
            t = dot3(corner[i, 0] - o0, corner[i, 1] - o1, corner[i, 2] - o2,
                     n0, n1, n2) / denom
            t32 = np.float32(t)
            if not (denom < 0 and t > 0 and t32 <= tmax[r] and t32 < best_t[r]):
                continue
            r0 = (o0 + t * d0) - corner[i, 0]
            r1 = (o1 + t * d1) - corner[i, 1]
            r2 = (o2 + t * d2) - corner[i, 2]
            a = dot3(r0, r1, r2, edge_u[i, 0], edge_u[i, 1], edge_u[i, 2]) / uu[i]
            b = dot3(r0, r1, r2, edge_v[i, 0], edge_v[i, 1], edge_v[i, 2]) / vv[i]
            if a >= 0 and a <= 1 and b >= 0 and b <= 1:
                best_t[r], best_l[r] = t32, i
    return best_t, best_l


@njit(**JIT)
def camera_rays(seed, width, height, pixel, sample, eye, fwd, right, up, half_w, half_h, near):
    """Jittered pinhole rays of (pixel, sample) pairs (n,) uint32 each, as
    `nprt.workers.wavefront.camera.generate_primary` defines them: eye, fwd, right, up (3,)
    float64 the camera frame, half_w, half_h the half extents of the image plane at unit
    distance, near the near-plane distance. Returns origin (n, 3) float64 on the near
    plane and direction (n, 3) float32 unit."""
    n = pixel.shape[0]
    origin = np.empty((n, 3), np.float64)
    direction = np.empty((n, 3), np.float32)
    kx, ky = dim_key(np.uint64(seed), np.uint64(0)), dim_key(np.uint64(seed), np.uint64(1))
    fw, fh = np.float64(width), np.float64(height)
    for r in range(n):
        px, sm = pixel[r], sample[r]
        jx = uniform_keyed(kx, px, sm, CAMERA_BOUNCE)
        jy = uniform_keyed(ky, px, sm, CAMERA_BOUNCE)
        x = (np.float64(px % np.uint32(width)) + jx) / fw * 2.0 - 1.0
        y = 1.0 - (np.float64(px // np.uint32(width)) + jy) / fh * 2.0
        sx, sy = x * half_w, y * half_h
        v0 = (fwd[0] + sx * right[0]) + sy * up[0]
        v1 = (fwd[1] + sx * right[1]) + sy * up[1]
        v2 = (fwd[2] + sx * right[2]) + sy * up[2]
        length = np.sqrt((v0 * v0 + v1 * v1) + v2 * v2)  # np.linalg.norm's order
        if not length > 0:
            length = 1.0
        u0, u1, u2 = (np.float32(v0 / length), np.float32(v1 / length),
                      np.float32(v2 / length))
        direction[r, 0], direction[r, 1], direction[r, 2] = u0, u1, u2
        w0, w1, w2 = np.float64(u0), np.float64(u1), np.float64(u2)
        t_near = near / dot3(w0, w1, w2, fwd[0], fwd[1], fwd[2])
        origin[r, 0] = eye[0] + t_near * w0
        origin[r, 1] = eye[1] + t_near * w1
        origin[r, 2] = eye[2] + t_near * w2
    return origin, direction
