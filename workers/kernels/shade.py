"""Jitted shading kernels: next-event light sampling, BSDF continuation and surface
interactions, row by row with exactly the float operations (and their order)
of the numpy formulas they replace, so film sums stay bit-identical. A wavefront's shading
is `shade_hits` (escaped rays, lights hit, emission, which hits go on), then `surface`,
`next_event` and `bsdf_continue` on those hits.

One fixed sum order, written out in the numpy oracles too (tests/workers/oracles.py):
three-term dot products, instance transforms included, sum (p0 + p2) + p1 (`_dot`), then
add a translation; norms sum (x0² + x1²) + x2² (`_norm`). These are also the orders numpy
2.x takes for `np.einsum("ij,ij->i")` and `np.linalg.norm(v, axis=1)` on C-ordered rows,
which the light formulas use (checked in tests/workers/test_shade_kernels.py). Sines and
cosines stay in numpy, whose SIMD versions need not round like libm.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from nprt.workers.kernels.records import LIGHT_BASE, NO_HIT  # the wire's fixed sentinels
from nprt.workers.kernels.rng import (
    DIM_BSDF_U,
    DIM_BSDF_V,
    DIM_LIGHT_BASE,
    DIM_RR,
    dim_key,
    uniform_keyed,
)

# error_model="numpy": x / 0.0 is inf or NaN (as in numpy), not a ZeroDivisionError.
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

# The rounding-error constants of the spawn offset (design: nprt.workers.kernels.offset).
# They live here, not there: numba's cache is keyed on this file, so a constant taken
# from another module would stay frozen in cached code after it changed.
# pbrt's gamma(n) = n u / (1 - n u), u the unit roundoff of the format.
_U32, _U64 = 2.0**-24, 2.0**-53
GAMMA32_7 = 7 * _U32 / (1 - 7 * _U32)
GAMMA64_3 = 3 * _U64 / (1 - 3 * _U64)
# Local error per unit of the hit triangle's largest |vertex coordinate|: |v - o| of any
# vertex v and a ray origin o near the triangle is at most twice that.
LOCAL_REL = 2 * GAMMA32_7
_LOCAL_REL = LOCAL_REL
# Floor of a light's cosine where it divides a pdf (the quad's solid-angle density, in
# next_event and in shade_hits' MIS weight of a quad hit): a grazing sample gets a huge,
# finite density (weight ~0), never a division by zero.
MIN_COS = 1e-30
# Russian roulette kills a path with probability 1 - max(throughput), at most this much,
# so no path is certain to die.
RR_MAX_KILL = 0.95
_G64 = GAMMA64_3
_G64_1 = 1.0 + GAMMA64_3
_TINY = 5e-324  # the least positive subnormal float64


@njit(inline="always", **JIT)
def _abs_rowdot(m, it, c, v0, v1, v2):
    """(|m[it, c, 0]| v0 + |m[it, c, 1]| v1) + |m[it, c, 2]| v2."""
    return (abs(m[it, c, 0]) * v0 + abs(m[it, c, 1]) * v1) + abs(m[it, c, 2]) * v2


@njit(inline="always", **JIT)
def _row_error(l2w, it, c, pl0, pl1, pl2, e):
    """Coordinate c of the local part of `point_error`'s bound."""
    a = ((abs(l2w[it, c, 0] * pl0) + abs(l2w[it, c, 1] * pl1))
         + abs(l2w[it, c, 2] * pl2)) + abs(l2w[it, c, 3])
    m = (abs(l2w[it, c, 0]) + abs(l2w[it, c, 1])) + abs(l2w[it, c, 2])
    return _G64 * a + _G64_1 * (m * e)


@njit(inline="always", **JIT)
def point_error(l2w, w2l, it, v_max, pl0, pl1, pl2, p0, p1, p2):
    """The oracle `hit_point_error` of world point (p0, p1, p2) float64 of instance it, from
    its local point (pl0, pl1, pl2) and its triangle's largest |local vertex coordinate|
    v_max: three float64. (Scalars, not rows of arrays: a store to an array may alias the
    tables, so LLVM would load them again after each one.)"""
    e = _LOCAL_REL * v_max
    o0 = _row_error(l2w, it, 0, pl0, pl1, pl2, e)
    o1 = _row_error(l2w, it, 1, pl0, pl1, pl2, e)
    o2 = _row_error(l2w, it, 2, pl0, pl1, pl2, e)
    q0, q1, q2 = abs(p0) + o0, abs(p1) + o1, abs(p2) + o2
    b0 = _G64 * (_abs_rowdot(w2l, it, 0, q0, q1, q2) + abs(w2l[it, 0, 3]))
    b1 = _G64 * (_abs_rowdot(w2l, it, 1, q0, q1, q2) + abs(w2l[it, 1, 3]))
    b2 = _G64 * (_abs_rowdot(w2l, it, 2, q0, q1, q2) + abs(w2l[it, 2, 3]))
    return (o0 + _abs_rowdot(l2w, it, 0, b0, b1, b2), o1 + _abs_rowdot(l2w, it, 1, b0, b1, b2),
            o2 + _abs_rowdot(l2w, it, 2, b0, b1, b2))


@intrinsic
def _bits(typingctx, x):
    """The bits of float64 x as an int64."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _from_bits(typingctx, b):
    """The float64 of bits b (int64)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


@njit(inline="always", **JIT)
def _step_away(o, up):
    """np.nextafter(o, inf if up else -inf), on the bits (libm's call cost ~10 ns): NaN
    and the infinity it moves to stay; zeros step to the least subnormal of that sign;
    any other value one ulp (the bits of a negative one count down to zero)."""
    if not (o < np.inf if up else o > -np.inf):
        return o
    if o == 0.0:
        return _TINY if up else -_TINY
    b = _bits(o)
    return _from_bits(b + 1 if (o > 0) == up else b - 1)


@njit(inline="always", **JIT)
def offset_origin(p, p_err, n, i, out, k):
    """out[k] = the oracle `offset_ray_origin` of row i of p, p_err, n (h, 3)
    float64, in float64 with its one-step rounding away from the surface."""
    n0, n1, n2 = n[i, 0], n[i, 1], n[i, 2]
    d = (abs(n0) * p_err[i, 0] + abs(n1) * p_err[i, 1]) + abs(n2) * p_err[i, 2]
    o0, o1, o2 = _offset1(p[i, 0], d * n0), _offset1(p[i, 1], d * n1), _offset1(p[i, 2], d * n2)
    out[k, 0], out[k, 1], out[k, 2] = o0, o1, o2


@njit(inline="always", **JIT)
def _offset1(x, off):
    """x + off, one ulp further in off's direction (none for 0 or NaN)."""
    o = x + off
    if off > 0:
        return _step_away(o, True)
    if off < 0:
        return _step_away(o, False)
    return o


@njit(inline="always", **JIT)
def _dot(a0, a1, a2, b0, b1, b2):
    """Three products in the fixed order (a0 b0 + a2 b2) + a1 b1."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@njit(inline="always", **JIT)
def _norm(a0, a1, a2):
    """The fixed order sqrt((a0² + a1²) + a2²)."""
    return np.sqrt((a0 * a0 + a1 * a1) + a2 * a2)


@njit(**JIT)
def next_event(seed, S, rows, ray_of, pixel, sample, depth, p, p_err, ns, ng, albedo, thr,
               q_corner, q_u, q_v, q_normal, q_area, q_radiance,
               pt_pos, pt_intensity, dir_dir, dir_irradiance, far_t, tmax_scale):
    """S light samples per row in `rows` (int64 indices into the per-hit arrays; hit i
    belongs to ray ray_of[i] of pixel, sample, depth), kept where the light is above both
    the shading and geometric surface and the contribution is positive (and not NaN).

    pixel, sample (n,) u32; depth (n,) u8 per ray; p, p_err, ns, ng, albedo, thr (h, 3)
    float64 per hit; light arrays as in `LightSet` (float64); far_t, tmax_scale float64.
    returns k and, in their first k rows: origin (m, 3) float64 (offset as
    `nprt.workers.kernels.offset`), direction (m, 3) float32,
    tmax (m,) float32, contribution (m, 3) float32, pixel (m,) uint32; m = len(rows) * S.
    """
    n_quads, n_points = len(q_area), len(pt_pos)
    count = n_quads + n_points + len(dir_dir)
    fcount = np.float64(count)
    fS = np.float64(S)
    m = len(rows) * S
    o_p = np.empty((m, 3), np.float64)
    o_dir = np.empty((m, 3), np.float32)
    o_tmax = np.empty(m, np.float32)
    o_con = np.empty((m, 3), np.float32)
    o_pix = np.empty(m, np.uint32)
    useed = np.uint64(seed)
    keys = np.empty(3 * S, np.uint64)
    for j in range(3 * S):
        keys[j] = dim_key(useed, np.uint64(DIM_LIGHT_BASE + j))  # light s, draw k: j = 3 s + k
    k = 0
    # The loop body is written out here, not in a row function: arrays passed to an
    # inlined function cost reference counts per call (the surface loop ran 2x slower).
    for r in range(len(rows)):
        i = rows[r]
        j = ray_of[i]
        px, sm, dp = pixel[j], sample[j], depth[j]
        # Per hit, not per sample: the same values (loads LLVM would repeat after each
        # store, as the output may alias the inputs; albedo / pi; the shadow origin).
        p0, p1, p2 = p[i, 0], p[i, 1], p[i, 2]
        ns0, ns1, ns2 = ns[i, 0], ns[i, 1], ns[i, 2]
        ng0, ng1, ng2 = ng[i, 0], ng[i, 1], ng[i, 2]
        t0, t1, t2 = thr[i, 0], thr[i, 1], thr[i, 2]
        a0, a1, a2 = albedo[i, 0] / np.pi, albedo[i, 1] / np.pi, albedo[i, 2] / np.pi
        first = k  # the row holding this hit's shadow origin, once one is kept
        for s in range(S):
            pick = uniform_keyed(keys[3 * s], px, sm, dp)
            u1 = uniform_keyed(keys[3 * s + 1], px, sm, dp)
            u2 = uniform_keyed(keys[3 * s + 2], px, sm, dp)
            li = min(np.int64(pick * fcount), count - 1)
            if li < n_quads:
                dist, pdf_l, w0, w1, w2, v0, v1, v2 = _sample_quad(
                    li, u1, u2, p0, p1, p2, q_corner, q_u, q_v, q_normal, q_area, q_radiance,
                    fcount)
            elif li < n_quads + n_points:
                dist, pdf_l, w0, w1, w2, v0, v1, v2 = _sample_point(
                    li - n_quads, p0, p1, p2, pt_pos, pt_intensity, fcount)
            else:
                ld = li - n_quads - n_points
                dist, pdf_l = far_t, 0.0
                w0, w1, w2 = -dir_dir[ld, 0], -dir_dir[ld, 1], -dir_dir[ld, 2]
                v0, v1, v2 = (dir_irradiance[ld, 0] * fcount, dir_irradiance[ld, 1] * fcount,
                              dir_irradiance[ld, 2] * fcount)
            ok, c0, c1, c2 = _light_contribution(w0, w1, w2, v0, v1, v2, pdf_l, fS, ns0, ns1,
                                                 ns2, ng0, ng1, ng2, a0, a1, a2, t0, t1, t2)
            if not ok:
                continue
            if k == first:
                offset_origin(p, p_err, ng, i, o_p, k)
            else:
                o_p[k, 0], o_p[k, 1], o_p[k, 2] = o_p[first, 0], o_p[first, 1], o_p[first, 2]
            o_dir[k, 0], o_dir[k, 1], o_dir[k, 2] = np.float32(w0), np.float32(w1), np.float32(w2)
            o_con[k, 0], o_con[k, 1], o_con[k, 2] = (np.float32(c0), np.float32(c1),
                                                     np.float32(c2))
            o_tmax[k] = np.float32(dist * tmax_scale)
            o_pix[k] = px
            k += 1
    return k, o_p, o_dir, o_tmax, o_con, o_pix


@njit(inline="always", **JIT)
def _sample_quad(li, u1, u2, p0, p1, p2, q_corner, q_u, q_v, q_normal, q_area, q_radiance,
                 fcount):
    """A point on quad li (uniform by area, u1 u2) seen from p: (distance, pdf_l, wi, val),
    wi its unit direction, val radiance over pdf (0 behind the quad) and pdf_l the
    solid-angle density of picking it (0 behind)."""
    v0 = ((q_corner[li, 0] + u1 * q_u[li, 0]) + u2 * q_v[li, 0]) - p0
    v1 = ((q_corner[li, 1] + u1 * q_u[li, 1]) + u2 * q_v[li, 1]) - p1
    v2 = ((q_corner[li, 2] + u1 * q_u[li, 2]) + u2 * q_v[li, 2]) - p2
    d = _norm(v0, v1, v2)
    dd = max(d, 1e-30)
    w0, w1, w2 = v0 / dd, v1 / dd, v2 / dd
    cos_l = -_dot(w0, w1, w2, q_normal[li, 0], q_normal[li, 1], q_normal[li, 2])
    if cos_l > 0:
        pdf_q = d * d / (max(cos_l, MIN_COS) * q_area[li]) / fcount
        return (d, pdf_q, w0, w1, w2, q_radiance[li, 0] / pdf_q, q_radiance[li, 1] / pdf_q,
                q_radiance[li, 2] / pdf_q)
    return d, 0.0, w0, w1, w2, 0.0, 0.0, 0.0


@njit(inline="always", **JIT)
def _sample_point(lp, p0, p1, p2, pt_pos, pt_intensity, fcount):
    """Point light lp seen from p: as `_sample_quad` (pdf_l 0)."""
    v0, v1, v2 = pt_pos[lp, 0] - p0, pt_pos[lp, 1] - p1, pt_pos[lp, 2] - p2
    d = _norm(v0, v1, v2)
    dd = max(d, 1e-30)
    d2 = max(d * d, 1e-30)
    return (d, 0.0, v0 / dd, v1 / dd, v2 / dd, pt_intensity[lp, 0] / d2 * fcount,
            pt_intensity[lp, 1] / d2 * fcount, pt_intensity[lp, 2] / d2 * fcount)


@njit(inline="always", **JIT)
def _light_contribution(w0, w1, w2, v0, v1, v2, pdf_l, fS, ns0, ns1, ns2, ng0, ng1, ng2, a0,
                        a1, a2, t0, t1, t2):
    """The MIS-weighted diffuse contribution of one light sample (direction w, radiance
    over pdf v) at a hit of shading and geometric normals ns, ng, albedo / pi a and
    throughput t: (kept, rgb), kept where the light is above both the shading and the
    geometric surface and the contribution is positive (and not NaN)."""
    cos_s = _dot(w0, w1, w2, ns0, ns1, ns2)
    cos_g = _dot(w0, w1, w2, ng0, ng1, ng2)
    if not (cos_s > 0 and cos_g > 0):
        return False, 0.0, 0.0, 0.0
    mc = max(cos_s, 0.0)
    pdf_b = mc / np.pi
    if pdf_l > 0:
        w = fS * pdf_l / (fS * pdf_l + pdf_b) / fS
    else:
        w = 1.0 / fS
    scale = mc * w
    c0 = t0 * a0 * v0 * scale
    c1 = t1 * a1 * v1 * scale
    c2 = t2 * a2 * v2 * scale
    if c0 != c0 or c1 != c1 or c2 != c2 or not (c0 > 0 or c1 > 0 or c2 > 0):
        return False, c0, c1, c2  # contrib.max(axis=1) > 0: NaN propagates and fails
    return True, c0, c1, c2


@njit(**JIT)
def surface(rows, inst, prim, u, v, direction, slot_of_mesh, inst_mesh, l2w, nmat, verts,
            faces, normals, uvs, mesh_vbase, mesh_fbase, mesh_has_n, mesh_has_uv, mesh_mat,
            mat_albedo, mat_emission, mat_tex, tex_base, tex_h, tex_w, texels, w2l):
    """Surface interactions of the oracle `surface_at` for `rows` (k,)
    int64 of the
    hit records inst, prim (n,) int32; u, v (n,) float32; direction (n, 3) float32.
    slot_of_mesh (M,) int64 base mesh -> slot here (-1: not held); inst_mesh (m,) int32;
    l2w (m, 3, 4), nmat (m, 3, 3) float64 (rows applied in `_dot`'s order);
    verts, normals (V, 3) float32; uvs (V, 2) float32; faces (F, 3) int64 (vertex base
    added). Per slot: vertex / face base, has-normals / has-uvs flags, material. Per
    material: albedo, emission (3,) float64, texture (-1: none). Per texture: texel base,
    height, width; texels (T, 3) float32; w2l (m, 3, 4) float64 (inverses of l2w).
    returns bad (the first of rows whose mesh is not held, else -1), p, ng, ns, albedo,
    emission, p_err (k, 3) float64 (p's error bound, the oracle `hit_point_error`).
    """
    n = len(rows)
    p = np.empty((n, 3))
    ng = np.empty((n, 3))
    ns = np.empty((n, 3))
    albedo = np.empty((n, 3))
    emission = np.empty((n, 3))
    p_err = np.empty((n, 3))
    for i in range(n):
        h = rows[i]
        it = inst[h]
        slot = slot_of_mesh[inst_mesh[it]]
        if slot < 0:
            return h, p, ng, ns, albedo, emission, p_err
        mat = mesh_mat[slot]
        b1, b2 = np.float64(u[h]), np.float64(v[h])
        b0 = 1.0 - b1 - b2
        f = mesh_fbase[slot] + prim[h]
        t0, t1, t2 = faces[f, 0], faces[f, 1], faces[f, 2]
        v_max, pl0, pl1, pl2, gl0, gl1, gl2, sl0, sl1, sl2 = _local_hit(
            verts, normals, mesh_has_n[slot], t0, t1, t2, b0, b1, b2)
        tx = mat_tex[mat]
        if tx >= 0 and mesh_has_uv[slot]:
            a0, a1, a2 = _texel(uvs, t0, t1, t2, b0, b1, b2, tex_base[tx], tex_h[tx],
                                tex_w[tx], texels)
        else:
            a0, a1, a2 = mat_albedo[mat, 0], mat_albedo[mat, 1], mat_albedo[mat, 2]
        p0 = _dot(l2w[it, 0, 0], l2w[it, 0, 1], l2w[it, 0, 2], pl0, pl1, pl2) + l2w[it, 0, 3]
        p1 = _dot(l2w[it, 1, 0], l2w[it, 1, 1], l2w[it, 1, 2], pl0, pl1, pl2) + l2w[it, 1, 3]
        p2 = _dot(l2w[it, 2, 0], l2w[it, 2, 1], l2w[it, 2, 2], pl0, pl1, pl2) + l2w[it, 2, 3]
        e0, e1, e2 = point_error(l2w, w2l, it, v_max, pl0, pl1, pl2, p0, p1, p2)
        g0, g1, g2, s0, s1, s2 = _world_normals(
            nmat, it, gl0, gl1, gl2, sl0, sl1, sl2, np.float64(direction[h, 0]),
            np.float64(direction[h, 1]), np.float64(direction[h, 2]))
        # Computed in scalars, stored at the end: a store to an array may alias the
        # tables, so LLVM would load them again after each one.
        p[i, 0], p[i, 1], p[i, 2] = p0, p1, p2
        p_err[i, 0], p_err[i, 1], p_err[i, 2] = e0, e1, e2
        ng[i, 0], ng[i, 1], ng[i, 2] = g0, g1, g2
        ns[i, 0], ns[i, 1], ns[i, 2] = s0, s1, s2
        albedo[i, 0], albedo[i, 1], albedo[i, 2] = a0, a1, a2
        emission[i, 0], emission[i, 1], emission[i, 2] = (
            mat_emission[mat, 0], mat_emission[mat, 1], mat_emission[mat, 2])
    return -1, p, ng, ns, albedo, emission, p_err


@njit(inline="always", **JIT)
def _bary(b0, b1, b2, x0, x1, x2):
    """b0 x0 + b1 x1 + b2 x2, left to right."""
    return b0 * x0 + b1 * x1 + b2 * x2


@njit(inline="always", **JIT)
def _local_hit(verts, normals, has_n, t0, t1, t2, b0, b1, b2):
    """Triangle (t0, t1, t2) at barycentrics b in local space, in float64: its largest
    |vertex coordinate|, point pl, geometric normal gl (np.cross's order, not unit) and
    shading normal sl (the vertex normals interpolated, or gl): ten float64."""
    x00, x01, x02 = np.float64(verts[t0, 0]), np.float64(verts[t0, 1]), np.float64(verts[t0, 2])
    x10, x11, x12 = np.float64(verts[t1, 0]), np.float64(verts[t1, 1]), np.float64(verts[t1, 2])
    x20, x21, x22 = np.float64(verts[t2, 0]), np.float64(verts[t2, 1]), np.float64(verts[t2, 2])
    pl0, pl1, pl2 = (_bary(b0, b1, b2, x00, x10, x20), _bary(b0, b1, b2, x01, x11, x21),
                     _bary(b0, b1, b2, x02, x12, x22))
    v_max = max(0.0, abs(x00), abs(x10), abs(x20))
    v_max = max(v_max, abs(x01), abs(x11), abs(x21))
    v_max = max(v_max, abs(x02), abs(x12), abs(x22))
    e10, e11, e12 = x10 - x00, x11 - x01, x12 - x02
    e20, e21, e22 = x20 - x00, x21 - x01, x22 - x02
    gl0 = e11 * e22 - e12 * e21  # np.cross's order
    gl1 = e12 * e20 - e10 * e22
    gl2 = e10 * e21 - e11 * e20
    if has_n:
        sl0 = _bary(b0, b1, b2, np.float64(normals[t0, 0]), np.float64(normals[t1, 0]),
                    np.float64(normals[t2, 0]))
        sl1 = _bary(b0, b1, b2, np.float64(normals[t0, 1]), np.float64(normals[t1, 1]),
                    np.float64(normals[t2, 1]))
        sl2 = _bary(b0, b1, b2, np.float64(normals[t0, 2]), np.float64(normals[t1, 2]),
                    np.float64(normals[t2, 2]))
    else:
        sl0, sl1, sl2 = gl0, gl1, gl2
    return v_max, pl0, pl1, pl2, gl0, gl1, gl2, sl0, sl1, sl2


@njit(inline="always", **JIT)
def _texel(uvs, t0, t1, t2, b0, b1, b2, base, th, tw, texels):
    """The nearest texel (wrapping; row (1 - v) h) of the texture at texels[base:] (th x tw)
    under the interpolated UV: three float64."""
    uu = _bary(b0, b1, b2, np.float64(uvs[t0, 0]), np.float64(uvs[t1, 0]),
               np.float64(uvs[t2, 0]))
    vv = _bary(b0, b1, b2, np.float64(uvs[t0, 1]), np.float64(uvs[t1, 1]),
               np.float64(uvs[t2, 1]))
    x = _wrap(np.int64(np.floor(_frac(uu) * tw)), tw)
    y = _wrap(np.int64(np.floor(_frac(1.0 - vv) * th)), th)
    t = base + y * tw + x
    return np.float64(texels[t, 0]), np.float64(texels[t, 1]), np.float64(texels[t, 2])


@njit(inline="always", **JIT)
def _frac(x):
    """x % 1.0 (Python's: in [0, 1), +0 for integers, NaN for infinities) without fmod: x
    - floor(x) is that value rounded once, as fmod's exact remainder plus 1 for x < 0 is."""
    return x - np.floor(x)


@njit(inline="always", **JIT)
def _wrap(k, n):
    """k % n for n > 0, the division skipped where k is already in [0, n)."""
    return k if 0 <= k < n else k % n


@njit(inline="always", **JIT)
def _world_normals(nmat, it, gl0, gl1, gl2, sl0, sl1, sl2, d0, d1, d2):
    """gl, sl moved by instance it's normal matrix and made unit (zero stays zero), both
    facing the side direction d came from (two-sided diffuse): ng, ns, six float64."""
    g0 = _dot(nmat[it, 0, 0], nmat[it, 0, 1], nmat[it, 0, 2], gl0, gl1, gl2)
    g1 = _dot(nmat[it, 1, 0], nmat[it, 1, 1], nmat[it, 1, 2], gl0, gl1, gl2)
    g2 = _dot(nmat[it, 2, 0], nmat[it, 2, 1], nmat[it, 2, 2], gl0, gl1, gl2)
    s0 = _dot(nmat[it, 0, 0], nmat[it, 0, 1], nmat[it, 0, 2], sl0, sl1, sl2)
    s1 = _dot(nmat[it, 1, 0], nmat[it, 1, 1], nmat[it, 1, 2], sl0, sl1, sl2)
    s2 = _dot(nmat[it, 2, 0], nmat[it, 2, 1], nmat[it, 2, 2], sl0, sl1, sl2)
    ln = _norm(g0, g1, g2)
    if not ln > 0:
        ln = 1.0
    g0, g1, g2 = g0 / ln, g1 / ln, g2 / ln
    ln = _norm(s0, s1, s2)
    if not ln > 0:
        ln = 1.0
    s0, s1, s2 = s0 / ln, s1 / ln, s2 / ln
    if _dot(g0, g1, g2, d0, d1, d2) > 0:
        g0, g1, g2 = -g0, -g1, -g2
    if _dot(s0, s1, s2, g0, g1, g2) < 0:
        s0, s1, s2 = -s0, -s1, -s2
    return g0, g1, g2, s0, s1, s2


@njit(**JIT)
def bsdf_continue(seed, rows, ray_of, pixel, sample, depth, cos_phi, sin_phi, p, p_err, ng,
                  ns, albedo, thr, russian_roulette, rr_start_depth):
    """Cosine-hemisphere continuation of `rows` (k,) int64 (of the oracle
    `cosine_hemisphere` and `PathIntegrator._continue`): cos_phi, sin_phi (k,) float64 of
    phi = 2 pi u2 come from numpy, whose SIMD sines need not round like libm's.

    ray_of (h,) int64 hit -> ray; pixel, sample (n,) u32; depth (n,) u8 per ray;
    p, p_err, ng, ns, albedo, thr (h, 3) float64 per hit.
    returns c and, in their first c rows: row (c,) int64 (into the per-hit arrays),
    origin (c, 3) float64 (offset as `nprt.workers.kernels.offset`), direction, throughput (c, 3)
    float32, pdf (c,) float32.
    """
    k = len(rows)
    o_row = np.empty(k, np.int64)
    o_p = np.empty((k, 3), np.float64)
    o_d = np.empty((k, 3), np.float32)
    o_t = np.empty((k, 3), np.float32)
    o_pdf = np.empty(k, np.float32)
    useed = np.uint64(seed)
    key_u = dim_key(useed, np.uint64(DIM_BSDF_U))
    key_rr = dim_key(useed, np.uint64(DIM_RR))
    c = 0
    for j in range(k):
        i = rows[j]
        ray = ray_of[i]
        px, sm, dp = pixel[ray], sample[ray], depth[ray]
        u1 = uniform_keyed(key_u, px, sm, dp)
        r = np.sqrt(u1)
        x, y = r * cos_phi[j], r * sin_phi[j]
        z = np.sqrt(max(0.0, 1.0 - u1))
        n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
        sign = 1.0 if n2 >= 0 else -1.0  # Duff et al. frame, as the oracle `frame`
        a = -1.0 / (sign + n2)
        b = n0 * n1 * a
        d0 = x * (1.0 + sign * (n0 * n0) * a) + y * b + z * n0
        d1 = x * (sign * b) + y * (sign + (n1 * n1) * a) + z * n1
        d2 = x * (-sign * n0) + y * (-n1) + z * n2
        if not _dot(d0, d1, d2, ng[i, 0], ng[i, 1], ng[i, 2]) > 0:
            continue  # below the true surface: absorbed
        t0, t1, t2 = thr[i, 0] * albedo[i, 0], thr[i, 1] * albedo[i, 1], thr[i, 2] * albedo[i, 2]
        if t0 != t0 or t1 != t1 or t2 != t2:
            continue  # t.max(axis=1) > 0 fails on NaN
        if russian_roulette and np.int64(dp) + 1 >= rr_start_depth:
            q = min(max(1.0 - max(max(t0, t1), t2), 0.0), RR_MAX_KILL)
            if not uniform_keyed(key_rr, px, sm, dp) >= q:
                continue
            s = 1.0 - q
            t0, t1, t2 = t0 / s, t1 / s, t2 / s
        if not max(max(t0, t1), t2) > 0:
            continue
        o_row[c] = i
        offset_origin(p, p_err, ng, i, o_p, c)
        o_d[c, 0], o_d[c, 1], o_d[c, 2] = np.float32(d0), np.float32(d1), np.float32(d2)
        o_t[c, 0], o_t[c, 1], o_t[c, 2] = np.float32(t0), np.float32(t1), np.float32(t2)
        o_pdf[c] = np.float32(z / np.pi)
        c += 1
    return c, o_row, o_p, o_d, o_t, o_pdf


# -- what a wavefront's shading adds around the kernels above -------------------------

_TWO_PI = 2.0 * np.pi  # phi = 2 pi u2, in numpy's order (the constant first)


@njit(**JIT)
def shade_hits(seed, bounces, S, direction, tmax, throughput, pixel, sample, depth, pdf_prev,
               hit_inst, env_sky, env_a, env_b, q_normal, q_area, q_radiance, n_lights,
               slot_of_mesh, inst_mesh, mesh_mat, mat_emission):
    """The part of `PathIntegrator.shade` before the surfaces, for rays (n,) with a final
    hit record (the RayBatch columns of those names): film contributions of escaped rays
    (environment), quad lights hit (MIS-weighted against S light samples of n_lights) and
    emissive surfaces, and the hits that go on (depth < bounces).

    env_sky: sky (horizon env_a to zenith env_b) or constant (radiance env_a), (3,)
    float64 each; q_normal (L, 3), q_area (L,), q_radiance (L, 3) float64; slot_of_mesh,
    inst_mesh, mesh_mat, mat_emission as `surface` takes them.
    returns bad (the first ray whose mesh is not held, else -1), m, f_pix (n,) uint32 and
    f_rgb (n, 3) float64 (the contributions in their first m rows; contributions of zero
    left out: they add nothing), then per hit that goes on (g,): go_ray int64 (its ray),
    thr (g, 3) float64 (its throughput), phi float64 (2 pi u2 of its BSDF sample).
    """
    n = pixel.shape[0]
    bad, g = -1, 0
    lit = False  # a surface hit here emits: then every surface hit adds thr * emission
    for j in range(n):
        it = hit_inst[j]
        if it < 0:
            continue
        slot = slot_of_mesh[inst_mesh[it]]
        if slot < 0:
            bad, g = j, 0
            break
        mat = mesh_mat[slot]
        if mat_emission[mat, 0] != 0 or mat_emission[mat, 1] != 0 or mat_emission[mat, 2] != 0:
            lit = True
        if depth[j] < bounces:
            g += 1
    f_pix = np.empty(n, np.uint32)
    f_rgb = np.empty((n, 3))
    go_ray = np.empty(g, np.int64)
    thr = np.empty((g, 3))
    phi = np.empty(g)
    if bad >= 0:
        return bad, 0, f_pix, f_rgb, go_ray, thr, phi
    key_v = dim_key(np.uint64(seed), np.uint64(DIM_BSDF_V))
    fS, fcount = np.float64(S), np.float64(n_lights)
    m = i = 0
    for j in range(n):
        it = hit_inst[j]
        t0, t1, t2 = (np.float64(throughput[j, 0]), np.float64(throughput[j, 1]),
                      np.float64(throughput[j, 2]))
        emit = True
        if it == NO_HIT:
            if env_sky:
                y = np.float64(direction[j, 1])
                w = 0.0 if y < 0.0 else (1.0 if y > 1.0 else y)  # np.clip: NaN stays NaN
                v0 = t0 * ((1 - w) * env_a[0] + w * env_b[0])
                v1 = t1 * ((1 - w) * env_a[1] + w * env_b[1])
                v2 = t2 * ((1 - w) * env_a[2] + w * env_b[2])
            else:
                v0, v1, v2 = t0 * env_a[0], t1 * env_a[1], t2 * env_a[2]
        elif it < NO_HIT:
            li = LIGHT_BASE - it
            w = 1.0  # camera rays, and S = 0: no MIS
            if S > 0:
                cos_l = abs(_dot(np.float64(direction[j, 0]), np.float64(direction[j, 1]),
                                 np.float64(direction[j, 2]), q_normal[li, 0],
                                 q_normal[li, 1], q_normal[li, 2]))
                cos_l = MIN_COS if cos_l < MIN_COS else cos_l  # np.maximum: NaN stays
                tt = np.float64(tmax[j])
                pdf_l = fS * (tt * tt / ((cos_l * q_area[li]) * fcount))
                pdf_b = np.float64(pdf_prev[j])
                if pdf_b > 0:
                    w = pdf_b / (pdf_b + pdf_l)
            v0 = t0 * (q_radiance[li, 0] * w)
            v1 = t1 * (q_radiance[li, 1] * w)
            v2 = t2 * (q_radiance[li, 2] * w)
        else:
            mat = mesh_mat[slot_of_mesh[inst_mesh[it]]]
            emit = lit
            v0, v1, v2 = (t0 * mat_emission[mat, 0], t1 * mat_emission[mat, 1],
                          t2 * mat_emission[mat, 2])
            if depth[j] < bounces:
                go_ray[i] = j
                thr[i, 0], thr[i, 1], thr[i, 2] = t0, t1, t2
                phi[i] = _TWO_PI * uniform_keyed(key_v, pixel[j], sample[j], depth[j])
                i += 1
        if emit and (v0 != 0 or v1 != 0 or v2 != 0):  # NaN is kept
            f_pix[m] = pixel[j]
            f_rgb[m, 0], f_rgb[m, 1], f_rgb[m, 2] = v0, v1, v2
            m += 1
    return -1, m, f_pix, f_rgb, go_ray, thr, phi
