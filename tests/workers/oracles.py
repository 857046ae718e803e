"""Numpy oracles of the renderer's jitted kernels, kept for the tests alone: each is the
plain formula a kernel must match bit for bit (`surface_at` for
`nprt.workers.kernels.shade.surface`, `hit_point_error` and `offset_ray_origin` for its
`point_error` and `offset_origin`, `sample_lights` for `next_event`'s light sampling,
`cosine_hemisphere` for `bsdf_continue`, `uniform` for rng's compiled hash (through
`tests.workers.rng_rows.uniform`), `intersect_quads` and `generate_primary` for
`nprt.workers.kernels.quads`, `environment_radiance` and `pdf_quad_hit` for `shade_hits`).
No product code imports this module."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numba import njit

from nprt.scene.model import Camera, Material, Mesh
from nprt.workers.kernels.pairs import to_local_ray
from nprt.workers.kernels.shade import GAMMA64_3, LOCAL_REL, MIN_COS, offset_origin
from nprt.workers.routing.exact import DONE, first_of_runs
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.lights import FAR_T, LightSet
from nprt.workers.wavefront.surface import Surface
from nprt.workers.wavefront.world import ShardWorld


def surface_at(meshes: Mapping[int, Mesh], materials: Sequence[Material],
               table: InstanceTable, inst: np.ndarray, prim: np.ndarray,
               u: np.ndarray, v: np.ndarray, direction: np.ndarray) -> Surface:
    """inst, prim (n,) int32; u, v (n,) float32 barycentrics; direction (n,3) f32 incoming.
    The numpy formula, kept as the oracle of `SurfaceTables.at`."""
    n = len(inst)
    p_loc = np.zeros((n, 3))
    v_max = np.zeros(n)  # largest |local vertex coordinate| of each hit triangle
    ng_loc = np.zeros((n, 3))
    ns_loc = np.zeros((n, 3))
    albedo = np.zeros((n, 3))
    emission = np.zeros((n, 3))
    mesh_of = table.mesh[inst]
    b1, b2 = u.astype(np.float64), v.astype(np.float64)
    b0 = 1.0 - b1 - b2
    for m in np.unique(mesh_of):
        sel = mesh_of == m
        mesh = meshes[m]
        tri = mesh.faces[prim[sel]]  # (s, 3) vertex indices
        v0, v1, v2 = (mesh.vertices[tri[:, k]].astype(np.float64) for k in range(3))
        w0, w1, w2 = b0[sel, None], b1[sel, None], b2[sel, None]
        p_loc[sel] = w0 * v0 + w1 * v1 + w2 * v2
        v_max[sel] = np.abs(np.stack([v0, v1, v2], axis=1)).max(axis=(1, 2))
        ng_loc[sel] = np.cross(v1 - v0, v2 - v0)
        if mesh.normals is not None:
            nv = mesh.normals.astype(np.float64)
            ns_loc[sel] = w0 * nv[tri[:, 0]] + w1 * nv[tri[:, 1]] + w2 * nv[tri[:, 2]]
        else:
            ns_loc[sel] = ng_loc[sel]
        mat = materials[mesh.material]
        if mat.texture is not None and mesh.uvs is not None:
            uv = w0 * mesh.uvs[tri[:, 0]] + w1 * mesh.uvs[tri[:, 1]] + w2 * mesh.uvs[tri[:, 2]]
            albedo[sel] = _lookup(mat.texture, uv)
        else:
            albedo[sel] = mat.albedo
        emission[sel] = mat.emission
    l2w = table.local_to_world[inst]  # (n, 3, 4)
    p = _apply(l2w, p_loc) + l2w[:, :, 3]
    p_err = hit_point_error(v_max, p_loc, l2w, table.world_to_local[inst], p)
    nmat = table.normal_to_world[inst]
    ng = _unit(_apply(nmat, ng_loc))
    ns = _unit(_apply(nmat, ns_loc))
    d = direction.astype(np.float64)
    # Two-sided diffuse: both normals face the side the ray came from.
    ng = np.where((_dot(ng, d) > 0)[:, None], -ng, ng)
    ns = np.where((_dot(ns, ng) < 0)[:, None], -ns, ns)
    return Surface(p, ng, ns, albedo, emission, p_err)


# The kernels' fixed sum orders (`shade_kernels._dot`, `_norm`), written out rather than
# left to np.einsum / np.linalg.norm, whose order may follow the operands' memory layout.
def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row dot products (a0 b0 + a2 b2) + a1 b1 of a, b (n, 3) float64 -> (n,)."""
    return (a[:, 0] * b[:, 0] + a[:, 2] * b[:, 2]) + a[:, 1] * b[:, 1]


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """m[:, :, :3] (n, 3, >= 3) float64 times x (n, 3) float64, each row by `_dot`."""
    q = m[:, :, :3] * x[:, None, :]  # (n, 3, 3) products
    return (q[..., 0] + q[..., 2]) + q[..., 1]


def _unit(v: np.ndarray) -> np.ndarray:
    """(n, 3) -> unit rows, length sqrt((v0² + v1²) + v2²); zero rows stay zero."""
    length = np.sqrt((v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]) + v[:, 2] * v[:, 2])[:, None]
    return v / np.where(length > 0, length, 1.0)


def _lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest texel with wrapping. texture (h, w, 3) float32, uv (n, 2) -> (n, 3) float64."""
    h, w = texture.shape[:2]
    x = np.floor(np.mod(uv[:, 0], 1.0) * w).astype(np.int64) % w
    y = np.floor(np.mod(1.0 - uv[:, 1], 1.0) * h).astype(np.int64) % h
    return texture[y, x].astype(np.float64)


def _rowdot(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n, 3, k) m, (n, 3) v -> (n, 3): sum_j m[:, c, j] v[:, j], summed (0 + 1) + 2."""
    return (m[..., 0] * v[:, None, 0] + m[..., 1] * v[:, None, 1]) + m[..., 2] * v[:, None, 2]


def hit_point_error(v_max: np.ndarray, p_loc: np.ndarray, l2w: np.ndarray, w2l: np.ndarray,
                    p: np.ndarray) -> np.ndarray:
    """Per-coordinate bound on the world error of hit points, including the trip of a ray
    origin back into the instance's local space.

    v_max : (n,) float64 largest |coordinate| of the hit triangle's local vertices;
    p_loc : (n, 3) float64 local hit points; l2w, w2l : (n, 3, 4) float64 instance
    transforms; p : (n, 3) float64 world points
    returns (n, 3) float64
    """
    e_loc = LOCAL_REL * v_max  # (n,) the same on every local axis
    m = np.abs(l2w)
    mx = np.abs(l2w[:, :, :3] * p_loc[:, None, :])  # (n, 3, 3) |M_cj x_j|
    a = ((mx[..., 0] + mx[..., 1]) + mx[..., 2]) + m[..., 3]
    e_world = GAMMA64_3 * a + (1.0 + GAMMA64_3) * (((m[..., 0] + m[..., 1]) + m[..., 2])
                                                     * e_loc[:, None])
    w = np.abs(w2l)
    e_back = GAMMA64_3 * (_rowdot(w, np.abs(p) + e_world) + w[..., 3])  # local units
    return e_world + _rowdot(m, e_back)


def offset_ray_origin(p: np.ndarray, p_err: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Push points off their surface to the side that `n` points to, past their error.

    p, p_err : (n, 3) float64 world hit points and their error bounds;
    n : (n, 3) float64 unit geometric normals toward the side the new rays leave from
    returns (n, 3) float64
    """
    an = np.abs(n)
    d = (an[:, 0] * p_err[:, 0] + an[:, 1] * p_err[:, 1]) + an[:, 2] * p_err[:, 2]
    off = d[:, None] * n
    o = p + off
    return np.where(off > 0, np.nextafter(o, np.inf),
                    np.where(off < 0, np.nextafter(o, -np.inf), o))


def frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent and bitangent for unit normals (n, 3) float64 (Duff et al. 2017, branchless)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, s


def cosine_hemisphere(u1: np.ndarray, u2: np.ndarray, n: np.ndarray):
    """Cosine-weighted directions about unit normals.

    u1, u2 : (k,) float64 in [0, 1); n : (k, 3) float64
    returns direction (k, 3) float64 unit, pdf (k,) float64 solid-angle density cos/pi
    """
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    x, y = r * np.cos(phi), r * np.sin(phi)
    z = np.sqrt(np.maximum(0.0, 1.0 - u1))
    t, s = frame(n)
    d = x[:, None] * t + y[:, None] * s + z[:, None] * n
    return d, z / np.pi


def sample_lights(lights: LightSet, pick: np.ndarray, u1: np.ndarray, u2: np.ndarray,
                  p: np.ndarray):
    """One of `lights` sampled per row from points p, as `next_event` does.

    pick, u1, u2 : (n,) float64 uniforms; p : (n, 3) float64 shading points
    returns wi (n, 3) f64 unit, dist (n,) f64 (FAR_T for directional),
    radiance_over_pdf (n, 3) f64 = Le * G-terms / pdf excluding the receiver cosine,
    pdf_solid (n,) f64 for MIS (0 for delta lights, meaning no MIS).
    """
    n = len(p)
    idx = np.minimum((pick * lights.count).astype(np.int64), lights.count - 1)
    wi = np.zeros((n, 3))
    dist = np.full(n, float(FAR_T))
    value = np.zeros((n, 3))
    pdf = np.zeros(n)
    q = idx < lights.n_quads
    if q.any():
        li = idx[q]
        y = (lights.quad_corner[li] + u1[q, None] * lights.quad_u[li]
             + u2[q, None] * lights.quad_v[li])
        v = y - p[q]
        d = np.linalg.norm(v, axis=1)
        w = v / np.maximum(d, 1e-30)[:, None]
        cos_l = -np.einsum("ij,ij->i", w, lights.quad_normal[li])
        pdf_q = np.where(cos_l > 0, d**2 / (np.maximum(cos_l, 1e-30) * lights.quad_area[li]), 0.0)
        pdf_q = pdf_q / lights.count
        ok = cos_l > 0
        wi[q], dist[q], pdf[q] = w, d, np.where(ok, pdf_q, 0.0)
        value[q] = np.where(ok[:, None], lights.quad_radiance[li] /
                            np.where(ok, pdf_q, 1.0)[:, None], 0.0)
    pt = (idx >= lights.n_quads) & (idx < lights.n_quads + lights.n_points)
    if pt.any():
        li = idx[pt] - lights.n_quads
        v = lights.point_pos[li] - p[pt]
        d = np.linalg.norm(v, axis=1)
        wi[pt], dist[pt] = v / np.maximum(d, 1e-30)[:, None], d
        value[pt] = lights.point_intensity[li] / np.maximum(d**2, 1e-30)[:, None] * lights.count
    dl = idx >= lights.n_quads + lights.n_points
    if dl.any():
        li = idx[dl] - lights.n_quads - lights.n_points
        wi[dl] = -lights.dir_dir[li]
        value[dl] = lights.dir_irradiance[li] * lights.count
    return wi, dist, value, pdf


def environment_radiance(lights: LightSet, direction: np.ndarray) -> np.ndarray:
    """(n, 3) float32 unit directions -> (n, 3) float64 radiance of escaped rays (the
    numpy formula of `nprt.workers.kernels.shade.shade_hits`' environment)."""
    env = lights.environment
    if env.kind == "sky":
        w = np.clip(direction[:, 1].astype(np.float64), 0.0, 1.0)[:, None]
        return (1 - w) * np.asarray(env.horizon)[None] + w * np.asarray(env.zenith)[None]
    return np.broadcast_to(np.asarray(env.radiance, np.float64), (len(direction), 3))


def pdf_quad_hit(lights: LightSet, light: np.ndarray, t: np.ndarray,
                 direction: np.ndarray) -> np.ndarray:
    """Solid-angle pdf with which next-event estimation would have sampled this quad
    point, the 1/count light pick included (`shade_hits`' MIS weight of a quad hit).
    light (n,) int; direction (n, 3); t (n,) -> (n,) float64."""
    cos_l = np.abs(np.einsum("ij,ij->i", direction.astype(np.float64),
                             lights.quad_normal[light]))
    area = lights.quad_area[light]
    with np.errstate(divide="ignore"):
        return (t.astype(np.float64) ** 2) / (np.maximum(cos_l, MIN_COS) * area * lights.count)


@njit(cache=False)
def offset_rows(p, p_err, n):
    """The kernel `offset_origin` over (k, 3) float64 p, p_err and n, row by row (checked
    against `offset_ray_origin`)."""
    out = np.empty_like(p)
    for i in range(len(p)):
        offset_origin(p, p_err, n, i, out, i)
    return out


_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser, (n,) uint64 -> (n,) uint64 (wrapping arithmetic)."""
    x = (x ^ (x >> _S30)) * _M1
    x = (x ^ (x >> _S27)) * _M2
    return x ^ (x >> _S31)


def uniform(seed: int, pixel: np.ndarray, sample: np.ndarray, bounce, dim) -> np.ndarray:
    """The counter RNG in numpy: pixel, sample (n,) uint32; bounce, dim int or (n,);
    returns (n,) float64 in [0, 1)."""
    with np.errstate(over="ignore"):
        key = _mix(np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
                   + _GOLDEN * (np.asarray(dim, dtype=np.uint64) + np.uint64(1)))
        x = key ^ (pixel.astype(np.uint64) << np.uint64(32)) ^ sample.astype(np.uint64)
        x = _mix(x)
        x = _mix(x ^ (np.asarray(bounce, dtype=np.uint64) * _GOLDEN))
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def intersect_quads(lights: LightSet, origin: np.ndarray, direction: np.ndarray,
                    tmax: np.ndarray):
    """`nprt.workers.kernels.quads.intersect_quads` in numpy (its three-term dot products
    are numpy's float64 `(n, 3) @ (3,)`, through BLAS). origin (n, 3) float64, direction
    (n, 3) float32, tmax (n,) float32 -> t (n,) float32 (inf), light (n,) int32 (-1)."""
    n = len(origin)
    best_t = np.full(n, np.inf, np.float32)
    best_l = np.full(n, -1, np.int32)
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    for i in range(lights.n_quads):
        nrm = lights.quad_normal[i]
        denom = d @ nrm  # < 0 when arriving at the emitting face
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = ((lights.quad_corner[i] - o) @ nrm) / denom
            t32 = t.astype(np.float32)
            rel = o + t[:, None] * d - lights.quad_corner[i]
            a = rel @ lights.quad_u[i] / (lights.quad_u[i] @ lights.quad_u[i])
            b = rel @ lights.quad_v[i] / (lights.quad_v[i] @ lights.quad_v[i])
        ok = (denom < 0) & (t > 0) & (t32 <= tmax) & (t32 < best_t) & \
             (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        best_t[ok] = t32[ok]
        best_l[ok] = i
    return best_t, best_l


def generate_primary(cam: Camera, width: int, height: int, seed: int, pixel: np.ndarray,
                     sample: np.ndarray):
    """`nprt.workers.wavefront.camera.generate_primary` in numpy: origin (n, 3) float64,
    direction (n, 3) float32 of (pixel, sample) (n,) uint32 pairs."""
    from nprt.workers.kernels.rng import CAMERA_BOUNCE
    from nprt.workers.kernels.sampling import normalize
    from nprt.workers.wavefront.camera import camera_frame
    from tests.workers.rng_rows import uniform as rng_uniform

    eye, fwd, right, up, half_w, half_h = camera_frame(cam, width, height)
    jx = rng_uniform(seed, pixel, sample, CAMERA_BOUNCE, 0)
    jy = rng_uniform(seed, pixel, sample, CAMERA_BOUNCE, 1)
    x = (pixel % width + jx) / width * 2.0 - 1.0
    y = 1.0 - (pixel // width + jy) / height * 2.0
    d = fwd[None] + (x * half_w)[:, None] * right[None] + (y * half_h)[:, None] * up[None]
    direction = normalize(d).astype(np.float32)
    unit = direction.astype(np.float64)
    t_near = cam.near_distance / (unit @ fwd)
    origin = eye[None] + t_near[:, None] * unit
    return origin, direction


def to_local(table: InstanceTable, inst: np.ndarray, origin: np.ndarray,
             direction: np.ndarray):
    """Rays moved into their instance's local space by the traversal kernels' own inlined
    step: inst (n,) int32; origin, direction (n, 3) world. Returns origin, direction
    (n, 3) float32 local (direction not renormalised, so t is the same in both spaces)."""
    return _to_local(np.asarray(inst, np.int32), table.world_to_local,
                     np.array(origin, np.float64, order="C"),
                     np.array(direction, np.float64, order="C"))


@njit(cache=True)
def _to_local(inst, world_to_local, origin, direction):
    n = inst.shape[0]
    lo, ld = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    for x in range(n):
        lo[x, 0], lo[x, 1], lo[x, 2], ld[x, 0], ld[x, 1], ld[x, 2] = to_local_ray(
            world_to_local, inst[x], origin, direction, x)
    return lo, ld


def nearest_by_crossings(world: ShardWorld, remote: np.ndarray, origin, direction, box_tmax,
                         visited: np.ndarray) -> np.ndarray:
    """The definition `nprt.workers.routing.exact.nearest_unvisited` and the walks' routing
    search (`nprt.workers.kernels.nearest`) must match: list every crossing of an
    unvisited shard's box before box_tmax (n,) float64 (tmax already stretched), sort by
    (ray, t_enter, owner), take each ray's first. Returns (n,) int32 shard or DONE."""
    target = np.full(len(origin), DONE, np.int32)
    ray, inst, t_enter, _ = world.table.box_entries(origin, direction, box_tmax, remote)
    if len(ray) == 0:
        return target
    owner = world.owner[inst]
    fresh = (visited[ray] >> owner.astype(np.uint64)) & np.uint64(1) == 0
    ray, owner, t_enter = ray[fresh], owner[fresh], t_enter[fresh]
    order = np.lexsort((owner, t_enter, ray))
    ray, owner = ray[order], owner[order]
    first = first_of_runs(ray)
    target[ray[first]] = owner[first]
    return target
