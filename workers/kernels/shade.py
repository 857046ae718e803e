"""Jitted shading kernels: next-event light sampling, BSDF continuation and surface
interactions, row by row with exactly the float operations (and their order)
of the numpy formulas they replace, so film sums stay bit-identical. A wavefront's shading
runs as two of them (`shade_hits`, then `scatter`) built of the same row functions.

One fixed sum order, written out in the numpy oracles too (tests/workers/oracles.py):
three-term dot products, instance transforms included, sum (p0 + p2) + p1 (`_dot`), then
add a translation; norms sum (x0² + x1²) + x2² (`_norm`). These are also the orders numpy
2.x takes for `np.einsum("ij,ij->i")` and `np.linalg.norm(v, axis=1)` on C-ordered rows,
which the light formulas use (checked in tests/workers/test_shade_kernels.py). Sines and
cosines stay in numpy, whose SIMD versions need not round like libm.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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


@njit(inline="always", **JIT)
def _abs_rowdot(m, it, c, v0, v1, v2):
    """(|m[it, c, 0]| v0 + |m[it, c, 1]| v1) + |m[it, c, 2]| v2."""
    return (abs(m[it, c, 0]) * v0 + abs(m[it, c, 1]) * v1) + abs(m[it, c, 2]) * v2


@njit(inline="always", **JIT)
def point_error(l2w, w2l, it, v_max, pl, p, i, out):
    """out[i] = the oracle `hit_point_error` of world point p[i] (3,) float64 of
    instance it, from its local point pl (3,) float64 and its triangle's largest
    |local vertex coordinate| v_max."""
    e = _LOCAL_REL * v_max
    for c in range(3):
        a = ((abs(l2w[it, c, 0] * pl[0]) + abs(l2w[it, c, 1] * pl[1]))
             + abs(l2w[it, c, 2] * pl[2])) + abs(l2w[it, c, 3])
        m = (abs(l2w[it, c, 0]) + abs(l2w[it, c, 1])) + abs(l2w[it, c, 2])
        out[i, c] = _G64 * a + _G64_1 * (m * e)
    q0, q1, q2 = abs(p[i, 0]) + out[i, 0], abs(p[i, 1]) + out[i, 1], abs(p[i, 2]) + out[i, 2]
    b0 = _G64 * (_abs_rowdot(w2l, it, 0, q0, q1, q2) + abs(w2l[it, 0, 3]))
    b1 = _G64 * (_abs_rowdot(w2l, it, 1, q0, q1, q2) + abs(w2l[it, 1, 3]))
    b2 = _G64 * (_abs_rowdot(w2l, it, 2, q0, q1, q2) + abs(w2l[it, 2, 3]))
    for c in range(3):
        out[i, c] = out[i, c] + _abs_rowdot(l2w, it, c, b0, b1, b2)


@njit(inline="always", **JIT)
def offset_origin(p, p_err, n, i, out, k):
    """out[k] = the oracle `offset_ray_origin` of row i of p, p_err, n (h, 3)
    float64, in float64 with its one-step rounding away from the surface."""
    d = (abs(n[i, 0]) * p_err[i, 0] + abs(n[i, 1]) * p_err[i, 1]) + abs(n[i, 2]) * p_err[i, 2]
    for c in range(3):
        off = d * n[i, c]
        o = p[i, c] + off
        if off > 0:
            o = np.nextafter(o, np.inf)
        elif off < 0:
            o = np.nextafter(o, -np.inf)
        out[k, c] = o


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
    out = _shadow_out(len(rows) * S)
    keys = _light_keys(seed, S)
    wi, val = np.empty(3), np.empty(3)
    k = 0
    for r in range(len(rows)):
        i = rows[r]
        j = ray_of[i]
        k = _light_samples(keys, S, pixel[j], sample[j], depth[j], i, p, p_err, ns, ng,
                           albedo, thr, q_corner, q_u, q_v, q_normal, q_area, q_radiance,
                           pt_pos, pt_intensity, dir_dir, dir_irradiance, far_t, tmax_scale,
                           wi, val, out, k)
    o_p, o_dir, o_tmax, o_con, o_pix = out
    return k, o_p, o_dir, o_tmax, o_con, o_pix


@njit(inline="always", **JIT)
def _shadow_out(m):
    """Room for m shadow rays: origin (m, 3) float64, direction (m, 3) float32, tmax (m,)
    float32, contribution (m, 3) float32, pixel (m,) uint32."""
    return (np.empty((m, 3), np.float64), np.empty((m, 3), np.float32),
            np.empty(m, np.float32), np.empty((m, 3), np.float32), np.empty(m, np.uint32))


@njit(inline="always", **JIT)
def _light_keys(seed, S):
    """(3 S,) uint64 dimension keys of S light samples: light s, draw k at 3 s + k."""
    useed = np.uint64(seed)
    keys = np.empty(3 * S, np.uint64)
    for j in range(3 * S):
        keys[j] = dim_key(useed, np.uint64(DIM_LIGHT_BASE + j))
    return keys


@njit(inline="always", **JIT)
def _light_samples(keys, S, px, sm, dp, i, p, p_err, ns, ng, albedo, thr, q_corner, q_u, q_v,
                   q_normal, q_area, q_radiance, pt_pos, pt_intensity, dir_dir, dir_irradiance,
                   far_t, tmax_scale, wi, val, out, k):
    """The kept light samples of hit i (of the ray of pixel px, sample sm, depth dp),
    written to `out` (`_shadow_out`) from row k on; wi, val (3,) float64 scratch.
    Returns the next free row."""
    o_p, o_dir, o_tmax, o_con, o_pix = out
    n_quads, n_points = len(q_area), len(pt_pos)
    count = n_quads + n_points + len(dir_dir)
    fcount = np.float64(count)
    fS = np.float64(S)
    for s in range(S):
        pick = uniform_keyed(keys[3 * s], px, sm, dp)
        u1 = uniform_keyed(keys[3 * s + 1], px, sm, dp)
        u2 = uniform_keyed(keys[3 * s + 2], px, sm, dp)
        li = min(np.int64(pick * fcount), count - 1)
        if li < n_quads:
            dist, pdf_l = _sample_quad(li, u1, u2, p, i, q_corner, q_u, q_v, q_normal,
                                       q_area, q_radiance, fcount, wi, val)
        elif li < n_quads + n_points:
            dist, pdf_l = _sample_point(li - n_quads, p, i, pt_pos, pt_intensity, fcount,
                                        wi, val)
        else:
            dist, pdf_l = far_t, 0.0
            ld = li - n_quads - n_points
            for c in range(3):
                wi[c] = -dir_dir[ld, c]
                val[c] = dir_irradiance[ld, c] * fcount
        ok, c0, c1, c2 = _light_contribution(wi, val, pdf_l, fS, ns, ng, albedo, thr, i)
        if not ok:
            continue
        offset_origin(p, p_err, ng, i, o_p, k)
        for c in range(3):
            o_dir[k, c] = np.float32(wi[c])
        o_con[k, 0], o_con[k, 1], o_con[k, 2] = (np.float32(c0), np.float32(c1),
                                                 np.float32(c2))
        o_tmax[k] = np.float32(dist * tmax_scale)
        o_pix[k] = px
        k += 1
    return k


@njit(inline="always", **JIT)
def _sample_quad(li, u1, u2, p, i, q_corner, q_u, q_v, q_normal, q_area, q_radiance, fcount,
                 wi, val):
    """A point on quad li (uniform by area, u1 u2) seen from p[i]: wi (3,) its unit
    direction, val (3,) radiance over pdf (0 behind the quad). Returns (distance, pdf_l),
    pdf_l the solid-angle density of picking it (0 behind)."""
    v0 = ((q_corner[li, 0] + u1 * q_u[li, 0]) + u2 * q_v[li, 0]) - p[i, 0]
    v1 = ((q_corner[li, 1] + u1 * q_u[li, 1]) + u2 * q_v[li, 1]) - p[i, 1]
    v2 = ((q_corner[li, 2] + u1 * q_u[li, 2]) + u2 * q_v[li, 2]) - p[i, 2]
    d = _norm(v0, v1, v2)
    dd = max(d, 1e-30)
    wi[0], wi[1], wi[2] = v0 / dd, v1 / dd, v2 / dd
    cos_l = -_dot(wi[0], wi[1], wi[2], q_normal[li, 0], q_normal[li, 1], q_normal[li, 2])
    if cos_l > 0:
        pdf_q = d * d / (max(cos_l, MIN_COS) * q_area[li]) / fcount
        for c in range(3):
            val[c] = q_radiance[li, c] / pdf_q
        return d, pdf_q
    val[0] = val[1] = val[2] = 0.0
    return d, 0.0


@njit(inline="always", **JIT)
def _sample_point(lp, p, i, pt_pos, pt_intensity, fcount, wi, val):
    """Point light lp seen from p[i]: wi, val as `_sample_quad`; returns (distance, 0)."""
    v0, v1, v2 = pt_pos[lp, 0] - p[i, 0], pt_pos[lp, 1] - p[i, 1], pt_pos[lp, 2] - p[i, 2]
    d = _norm(v0, v1, v2)
    dd = max(d, 1e-30)
    wi[0], wi[1], wi[2] = v0 / dd, v1 / dd, v2 / dd
    d2 = max(d * d, 1e-30)
    for c in range(3):
        val[c] = pt_intensity[lp, c] / d2 * fcount
    return d, 0.0


@njit(inline="always", **JIT)
def _light_contribution(wi, val, pdf_l, fS, ns, ng, albedo, thr, i):
    """The MIS-weighted diffuse contribution of one light sample at hit i: (kept, rgb),
    kept where the light is above both the shading and the geometric surface and the
    contribution is positive (and not NaN)."""
    cos_s = _dot(wi[0], wi[1], wi[2], ns[i, 0], ns[i, 1], ns[i, 2])
    cos_g = _dot(wi[0], wi[1], wi[2], ng[i, 0], ng[i, 1], ng[i, 2])
    if not (cos_s > 0 and cos_g > 0):
        return False, 0.0, 0.0, 0.0
    mc = max(cos_s, 0.0)
    pdf_b = mc / np.pi
    if pdf_l > 0:
        w = fS * pdf_l / (fS * pdf_l + pdf_b) / fS
    else:
        w = 1.0 / fS
    scale = mc * w
    c0 = thr[i, 0] * (albedo[i, 0] / np.pi) * val[0] * scale
    c1 = thr[i, 1] * (albedo[i, 1] / np.pi) * val[1] * scale
    c2 = thr[i, 2] * (albedo[i, 2] / np.pi) * val[2] * scale
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
    scratch = (np.empty(3), np.empty(3), np.empty(3))
    out = (p, ng, ns, albedo, p_err)
    for i in range(n):
        h = rows[i]
        it = inst[h]
        slot = slot_of_mesh[inst_mesh[it]]
        if slot < 0:
            return h, p, ng, ns, albedo, emission, p_err
        mat = mesh_mat[slot]
        for c in range(3):
            emission[i, c] = mat_emission[mat, c]
        _surface_row(h, it, slot, mat, prim, u, v, direction, l2w, nmat, verts, faces, normals,
                     uvs, mesh_fbase, mesh_has_n, mesh_has_uv, mat_albedo, mat_tex, tex_base,
                     tex_h, tex_w, texels, w2l, scratch, out, i)
    return -1, p, ng, ns, albedo, emission, p_err


@njit(inline="always", **JIT)
def _surface_row(h, it, slot, mat, prim, u, v, direction, l2w, nmat, verts, faces, normals,
                 uvs, mesh_fbase, mesh_has_n, mesh_has_uv, mat_albedo, mat_tex, tex_base,
                 tex_h, tex_w, texels, w2l, scratch, out, i):
    """Row i of out = (p, ng, ns, albedo, p_err) (as `surface` documents them) for hit
    record h of instance it, whose mesh is in slot and has material mat; scratch: three
    (3,) float64. (At most 30 arguments: Python passes more as *args, which numba cannot
    inline.)"""
    pl, gl, sl = scratch
    p, ng, ns, albedo, p_err = out
    b1, b2 = np.float64(u[h]), np.float64(v[h])
    b0 = 1.0 - b1 - b2
    f = mesh_fbase[slot] + prim[h]
    t0, t1, t2 = faces[f, 0], faces[f, 1], faces[f, 2]
    v_max = _local_hit(verts, normals, mesh_has_n[slot], t0, t1, t2, b0, b1, b2, pl, gl, sl)
    tx = mat_tex[mat]
    if tx >= 0 and mesh_has_uv[slot]:
        _texel(uvs, t0, t1, t2, b0, b1, b2, tex_base[tx], tex_h[tx], tex_w[tx], texels,
               albedo, i)
    else:
        for c in range(3):
            albedo[i, c] = mat_albedo[mat, c]
    for c in range(3):
        p[i, c] = (_dot(l2w[it, c, 0], l2w[it, c, 1], l2w[it, c, 2], pl[0], pl[1], pl[2])
                   + l2w[it, c, 3])
    point_error(l2w, w2l, it, v_max, pl, p, i, p_err)
    _world_normals(nmat, it, gl, sl, direction, h, ng, ns, i)


@njit(inline="always", **JIT)
def _local_hit(verts, normals, has_n, t0, t1, t2, b0, b1, b2, pl, gl, sl):
    """Triangle (t0, t1, t2) at barycentrics b in local space, in float64: point pl (3,),
    geometric normal gl (3,) (np.cross's order, not unit), shading normal sl (3,) (the
    vertex normals interpolated, or gl). Returns the largest |vertex coordinate|."""
    v_max = 0.0
    for c in range(3):
        x0 = np.float64(verts[t0, c])
        pl[c] = b0 * x0 + b1 * np.float64(verts[t1, c]) + b2 * np.float64(verts[t2, c])
        v_max = max(v_max, abs(x0), abs(np.float64(verts[t1, c])),
                    abs(np.float64(verts[t2, c])))
    e10 = np.float64(verts[t1, 0]) - np.float64(verts[t0, 0])
    e11 = np.float64(verts[t1, 1]) - np.float64(verts[t0, 1])
    e12 = np.float64(verts[t1, 2]) - np.float64(verts[t0, 2])
    e20 = np.float64(verts[t2, 0]) - np.float64(verts[t0, 0])
    e21 = np.float64(verts[t2, 1]) - np.float64(verts[t0, 1])
    e22 = np.float64(verts[t2, 2]) - np.float64(verts[t0, 2])
    gl[0] = e11 * e22 - e12 * e21  # np.cross's order
    gl[1] = e12 * e20 - e10 * e22
    gl[2] = e10 * e21 - e11 * e20
    if has_n:
        for c in range(3):
            sl[c] = (b0 * np.float64(normals[t0, c]) + b1 * np.float64(normals[t1, c])
                     + b2 * np.float64(normals[t2, c]))
    else:
        sl[0], sl[1], sl[2] = gl[0], gl[1], gl[2]
    return v_max


@njit(inline="always", **JIT)
def _texel(uvs, t0, t1, t2, b0, b1, b2, base, th, tw, texels, albedo, i):
    """albedo[i] = the nearest texel (wrapping; row (1 - v) h) of the texture at texels[base:]
    (th x tw) under the interpolated UV."""
    uu = (b0 * np.float64(uvs[t0, 0]) + b1 * np.float64(uvs[t1, 0])
          + b2 * np.float64(uvs[t2, 0]))
    vv = (b0 * np.float64(uvs[t0, 1]) + b1 * np.float64(uvs[t1, 1])
          + b2 * np.float64(uvs[t2, 1]))
    x = np.int64(np.floor((uu % 1.0) * tw)) % tw
    y = np.int64(np.floor(((1.0 - vv) % 1.0) * th)) % th
    for c in range(3):
        albedo[i, c] = np.float64(texels[base + y * tw + x, c])


@njit(inline="always", **JIT)
def _world_normals(nmat, it, gl, sl, direction, h, ng, ns, i):
    """ng[i], ns[i] = gl, sl moved by instance it's normal matrix and made unit (zero stays
    zero), both facing the side ray h came from (two-sided diffuse)."""
    g0 = _dot(nmat[it, 0, 0], nmat[it, 0, 1], nmat[it, 0, 2], gl[0], gl[1], gl[2])
    g1 = _dot(nmat[it, 1, 0], nmat[it, 1, 1], nmat[it, 1, 2], gl[0], gl[1], gl[2])
    g2 = _dot(nmat[it, 2, 0], nmat[it, 2, 1], nmat[it, 2, 2], gl[0], gl[1], gl[2])
    s0 = _dot(nmat[it, 0, 0], nmat[it, 0, 1], nmat[it, 0, 2], sl[0], sl[1], sl[2])
    s1 = _dot(nmat[it, 1, 0], nmat[it, 1, 1], nmat[it, 1, 2], sl[0], sl[1], sl[2])
    s2 = _dot(nmat[it, 2, 0], nmat[it, 2, 1], nmat[it, 2, 2], sl[0], sl[1], sl[2])
    ln = _norm(g0, g1, g2)
    if not ln > 0:
        ln = 1.0
    g0, g1, g2 = g0 / ln, g1 / ln, g2 / ln
    ln = _norm(s0, s1, s2)
    if not ln > 0:
        ln = 1.0
    s0, s1, s2 = s0 / ln, s1 / ln, s2 / ln
    if _dot(g0, g1, g2, np.float64(direction[h, 0]), np.float64(direction[h, 1]),
            np.float64(direction[h, 2])) > 0:
        g0, g1, g2 = -g0, -g1, -g2
    if _dot(s0, s1, s2, g0, g1, g2) < 0:
        s0, s1, s2 = -s0, -s1, -s2
    ng[i, 0], ng[i, 1], ng[i, 2] = g0, g1, g2
    ns[i, 0], ns[i, 1], ns[i, 2] = s0, s1, s2


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
    out = _continue_out(k)
    key_u, key_rr = _bsdf_keys(seed)
    c = 0
    for j in range(k):
        i = rows[j]
        ray = ray_of[i]
        if _bsdf_sample(key_u, key_rr, pixel[ray], sample[ray], depth[ray], cos_phi[j],
                        sin_phi[j], i, p, p_err, ng, ns, albedo, thr, russian_roulette,
                        rr_start_depth, out, c):
            o_row[c] = i
            c += 1
    o_p, o_d, o_t, o_pdf = out
    return c, o_row, o_p, o_d, o_t, o_pdf


@njit(inline="always", **JIT)
def _continue_out(k):
    """Room for k continuation rays: origin (k, 3) float64, direction, throughput (k, 3)
    float32, pdf (k,) float32."""
    return (np.empty((k, 3), np.float64), np.empty((k, 3), np.float32),
            np.empty((k, 3), np.float32), np.empty(k, np.float32))


@njit(inline="always", **JIT)
def _bsdf_keys(seed):
    """The dimension keys of the BSDF's u1 and of Russian roulette (uint64)."""
    useed = np.uint64(seed)
    return dim_key(useed, np.uint64(DIM_BSDF_U)), dim_key(useed, np.uint64(DIM_RR))


@njit(inline="always", **JIT)
def _bsdf_sample(key_u, key_rr, px, sm, dp, cos_phi, sin_phi, i, p, p_err, ng, ns, albedo, thr,
                 russian_roulette, rr_start_depth, out, c):
    """The continuation of hit i (of the ray of pixel px, sample sm, depth dp) written to
    row c of `out` (`_continue_out`); False where the path ends (below the true surface,
    no throughput left, Russian roulette)."""
    o_p, o_d, o_t, o_pdf = out
    u1 = uniform_keyed(key_u, px, sm, dp)
    r = np.sqrt(u1)
    x, y = r * cos_phi, r * sin_phi
    z = np.sqrt(max(0.0, 1.0 - u1))
    n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
    sign = 1.0 if n2 >= 0 else -1.0  # Duff et al. frame, as the oracle `frame`
    a = -1.0 / (sign + n2)
    b = n0 * n1 * a
    d0 = x * (1.0 + sign * (n0 * n0) * a) + y * b + z * n0
    d1 = x * (sign * b) + y * (sign + (n1 * n1) * a) + z * n1
    d2 = x * (-sign * n0) + y * (-n1) + z * n2
    if not _dot(d0, d1, d2, ng[i, 0], ng[i, 1], ng[i, 2]) > 0:
        return False  # below the true surface: absorbed
    t0, t1, t2 = thr[i, 0] * albedo[i, 0], thr[i, 1] * albedo[i, 1], thr[i, 2] * albedo[i, 2]
    if t0 != t0 or t1 != t1 or t2 != t2:
        return False  # t.max(axis=1) > 0 fails on NaN
    if russian_roulette and np.int64(dp) + 1 >= rr_start_depth:
        q = min(max(1.0 - max(max(t0, t1), t2), 0.0), RR_MAX_KILL)
        if not uniform_keyed(key_rr, px, sm, dp) >= q:
            return False
        s = 1.0 - q
        t0, t1, t2 = t0 / s, t1 / s, t2 / s
    if not max(max(t0, t1), t2) > 0:
        return False
    offset_origin(p, p_err, ng, i, o_p, c)
    o_d[c, 0], o_d[c, 1], o_d[c, 2] = np.float32(d0), np.float32(d1), np.float32(d2)
    o_t[c, 0], o_t[c, 1], o_t[c, 2] = np.float32(t0), np.float32(t1), np.float32(t2)
    o_pdf[c] = np.float32(z / np.pi)
    return True


# -- one wavefront's shading in two kernels (numpy's sines between them) ----------------

_TWO_PI = 2.0 * np.pi  # phi = 2 pi u2, in numpy's order (the constant first)


@njit(**JIT)
def shade_hits(seed, bounces, S, direction, tmax, throughput, pixel, sample, depth, pdf_prev,
               hit_inst, hit_prim, hit_u, hit_v, env_sky, env_a, env_b, q_normal, q_area,
               q_radiance, n_lights, slot_of_mesh, inst_mesh, l2w, nmat, verts, faces, normals,
               uvs, mesh_vbase, mesh_fbase, mesh_has_n, mesh_has_uv, mesh_mat, mat_albedo,
               mat_emission, mat_tex, tex_base, tex_h, tex_w, texels, w2l):
    """The first half of `PathIntegrator.shade` for rays (n,) with a final hit record (the
    RayBatch columns of those names): film contributions of escaped rays (environment),
    quad lights hit (MIS-weighted against S light samples of n_lights) and emissive
    surfaces, and the surfaces of hits that go on (depth < bounces).

    env_sky: sky (horizon env_a to zenith env_b) or constant (radiance env_a), (3,)
    float64 each; q_normal (L, 3), q_area (L,), q_radiance (L, 3) float64;
    then the tables of `surface` (`SurfaceTables.kernel_tables()`).
    returns bad (the first ray whose mesh is not held, else -1), m, f_pix (n,) uint32 and
    f_rgb (n, 3) float64 (the contributions in the first m rows; rows of zero left out: they
    add nothing), then per hit that goes on (g,): go_ray int64 (its ray), p, p_err, ng, ns,
    albedo, thr (g, 3) float64 (thr: the ray's throughput), phi float64 (2 pi u2 of its
    BSDF sample).
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
    p, p_err, ng = np.empty((g, 3)), np.empty((g, 3)), np.empty((g, 3))
    ns, albedo, thr = np.empty((g, 3)), np.empty((g, 3)), np.empty((g, 3))
    phi = np.empty(g)
    if bad >= 0:
        return bad, 0, f_pix, f_rgb, go_ray, p, p_err, ng, ns, albedo, thr, phi
    key_v = dim_key(np.uint64(seed), np.uint64(DIM_BSDF_V))
    fS, fcount = np.float64(S), np.float64(n_lights)
    scratch = (np.empty(3), np.empty(3), np.empty(3))
    out = (p, ng, ns, albedo, p_err)
    m = i = 0
    for j in range(n):
        it = hit_inst[j]
        t0, t1, t2 = (np.float64(throughput[j, 0]), np.float64(throughput[j, 1]),
                      np.float64(throughput[j, 2]))
        if it == NO_HIT:
            if env_sky:
                y = np.float64(direction[j, 1])
                w = 0.0 if y < 0.0 else (1.0 if y > 1.0 else y)  # np.clip: NaN stays NaN
                m = _film(f_pix, f_rgb, m, pixel[j], t0 * ((1 - w) * env_a[0] + w * env_b[0]),
                          t1 * ((1 - w) * env_a[1] + w * env_b[1]),
                          t2 * ((1 - w) * env_a[2] + w * env_b[2]))
            else:
                m = _film(f_pix, f_rgb, m, pixel[j], t0 * env_a[0], t1 * env_a[1],
                          t2 * env_a[2])
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
            m = _film(f_pix, f_rgb, m, pixel[j], t0 * (q_radiance[li, 0] * w),
                      t1 * (q_radiance[li, 1] * w), t2 * (q_radiance[li, 2] * w))
        else:
            slot = slot_of_mesh[inst_mesh[it]]
            mat = mesh_mat[slot]
            if lit:
                m = _film(f_pix, f_rgb, m, pixel[j], t0 * mat_emission[mat, 0],
                          t1 * mat_emission[mat, 1], t2 * mat_emission[mat, 2])
            if depth[j] < bounces:
                go_ray[i] = j
                thr[i, 0], thr[i, 1], thr[i, 2] = t0, t1, t2
                _surface_row(j, it, slot, mat, hit_prim, hit_u, hit_v, direction, l2w, nmat,
                             verts, faces, normals, uvs, mesh_fbase, mesh_has_n, mesh_has_uv,
                             mat_albedo, mat_tex, tex_base, tex_h, tex_w, texels, w2l, scratch,
                             out, i)
                phi[i] = _TWO_PI * uniform_keyed(key_v, pixel[j], sample[j], depth[j])
                i += 1
    return -1, m, f_pix, f_rgb, go_ray, p, p_err, ng, ns, albedo, thr, phi


@njit(inline="always", **JIT)
def _film(f_pix, f_rgb, m, px, v0, v1, v2):
    """Add contribution (v0, v1, v2) of pixel px at row m unless it is zero (NaN is kept);
    returns the next free row."""
    if v0 != 0 or v1 != 0 or v2 != 0:
        f_pix[m] = px
        f_rgb[m, 0], f_rgb[m, 1], f_rgb[m, 2] = v0, v1, v2
        return m + 1
    return m


@njit(**JIT)
def scatter(seed, S, go_ray, pixel, sample, depth, p, p_err, ns, ng, albedo, thr, cos_phi,
            sin_phi, q_corner, q_u, q_v, q_normal, q_area, q_radiance, pt_pos, pt_intensity,
            dir_dir, dir_irradiance, far_t, tmax_scale, russian_roulette, rr_start_depth):
    """The second half of `PathIntegrator.shade`: `next_event` and `bsdf_continue` of the
    hits (g,) of `shade_hits` that go on, hit i of ray go_ray[i], in one loop. cos_phi,
    sin_phi (g,) float64 of its phi (numpy's); the light arrays as `next_event` takes them;
    S: 0 for no light samples.
    returns k and the shadow rays in the first k rows of origin (g S, 3) float64,
    direction (g S, 3) float32, tmax (g S,) float32, contribution (g S, 3) float32, pixel
    (g S,) uint32; then c and the continuation rays in the first c rows of origin (g, 3)
    float64, direction, throughput (g, 3) float32, pdf (g,) float32, pixel, sample (g,)
    uint32, depth (g,) uint8 (the hit's depth + 1).
    """
    g = go_ray.shape[0]
    shadow = _shadow_out(g * S)
    keys = _light_keys(seed, S)
    cont = _continue_out(g)
    key_u, key_rr = _bsdf_keys(seed)
    r_pix, r_sample, r_depth = np.empty(g, np.uint32), np.empty(g, np.uint32), np.empty(g, np.uint8)
    wi, val = np.empty(3), np.empty(3)
    k = c = 0
    for i in range(g):
        j = go_ray[i]
        px, sm, dp = pixel[j], sample[j], depth[j]
        k = _light_samples(keys, S, px, sm, dp, i, p, p_err, ns, ng, albedo, thr, q_corner,
                           q_u, q_v, q_normal, q_area, q_radiance, pt_pos, pt_intensity,
                           dir_dir, dir_irradiance, far_t, tmax_scale, wi, val, shadow, k)
        if _bsdf_sample(key_u, key_rr, px, sm, dp, cos_phi[i], sin_phi[i], i, p, p_err, ng, ns,
                        albedo, thr, russian_roulette, rr_start_depth, cont, c):
            r_pix[c], r_sample[c], r_depth[c] = px, sm, np.uint8(dp + 1)
            c += 1
    s_p, s_dir, s_tmax, s_con, s_pix = shadow
    o_p, o_d, o_t, o_pdf = cont
    return k, s_p, s_dir, s_tmax, s_con, s_pix, c, o_p, o_d, o_t, o_pdf, r_pix, r_sample, r_depth
