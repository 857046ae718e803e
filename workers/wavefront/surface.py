"""Surface interactions from hit records: position from barycentrics (float64, local then
world) with a bound on its rounding error (nprt.workers.kernels.offset), geometric and shading
normals,
UVs and albedo. Only meshes held here can be shaded."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from nprt.scene.model import Material, Mesh
from nprt.workers.kernels import shade as shade_kernels
from nprt.workers.kernels.offset import hit_point_error
from nprt.workers.traversal.toplevel import InstanceTable


@dataclass(frozen=True)
class Surface:
    """p (n,3) f64 world point; ng, ns (n,3) f64 unit geometric / shading normals facing
    the incoming ray; albedo (n,3) f64; emission (n,3) f64; p_err (n,3) f64 bound on p's
    rounding error per coordinate (`nprt.workers.kernels.offset.hit_point_error`)."""

    p: np.ndarray
    ng: np.ndarray
    ns: np.ndarray
    albedo: np.ndarray
    emission: np.ndarray
    p_err: np.ndarray


class SurfaceTables:
    """The meshes held here, their materials and the instance transforms, concatenated into
    the owned, writable arrays that `shade_kernels.surface` reads (built once per
    integrator; arrays read back from Ray's object store are read-only)."""

    def __init__(self, meshes: Mapping[int, Mesh], materials: Sequence[Material],
                 table: InstanceTable):
        held = sorted(meshes)
        n_base = max([*held, int(table.mesh.max(initial=-1))]) + 1
        self.slot_of_mesh = np.full(n_base, -1, np.int64)
        self.slot_of_mesh[held] = np.arange(len(held))
        ms = [meshes[m] for m in held]
        nv = np.array([len(m.vertices) for m in ms], np.int64)
        nf = np.array([len(m.faces) for m in ms], np.int64)
        self.vbase = np.concatenate([[0], np.cumsum(nv)[:-1]]).astype(np.int64)
        self.fbase = np.concatenate([[0], np.cumsum(nf)[:-1]]).astype(np.int64)

        def cat(parts, width, dtype):
            parts = [np.asarray(a, dtype).reshape(-1, width) for a in parts]
            return np.ascontiguousarray(np.concatenate([np.zeros((0, width), dtype), *parts]))

        self.verts = cat([m.vertices for m in ms], 3, np.float32)
        self.faces = cat([np.asarray(m.faces, np.int64) + b for m, b in zip(ms, self.vbase,
                                                                              strict=True)],
                         3, np.int64)
        self.normals = cat([m.normals if m.normals is not None else np.zeros((len(m.vertices), 3))
                            for m in ms], 3, np.float32)
        self.uvs = cat([m.uvs if m.uvs is not None else np.zeros((len(m.vertices), 2))
                        for m in ms], 2, np.float32)
        self.has_n = np.array([m.normals is not None for m in ms], np.bool_)
        self.has_uv = np.array([m.uvs is not None for m in ms], np.bool_)
        self.mesh_mat = np.array([m.material for m in ms], np.int64)
        self.mat_albedo = cat([m.albedo for m in materials], 3, np.float64)
        self.mat_emission = cat([m.emission for m in materials], 3, np.float64)
        textures = [m.texture for m in materials if m.texture is not None]
        self.mat_tex = np.full(len(materials), -1, np.int64)
        self.mat_tex[[i for i, m in enumerate(materials) if m.texture is not None]] = \
            np.arange(len(textures))
        self.tex_h = np.array([t.shape[0] for t in textures], np.int64)
        self.tex_w = np.array([t.shape[1] for t in textures], np.int64)
        sizes = self.tex_h * self.tex_w
        self.tex_base = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.texels = cat(textures, 3, np.float32)
        self.inst_mesh = np.array(table.mesh, np.int32)
        self.l2w = np.array(table.local_to_world, np.float64, order="C")
        self.nmat = np.array(table.normal_to_world, np.float64, order="C")
        self.w2l = np.array(table.world_to_local, np.float64, order="C")
        self.held = held

    def at(self, inst: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
           direction: np.ndarray, rows: np.ndarray | None = None) -> Surface:
        """`surface_at` through the kernel (bit-identical); the same arguments, and
        optionally rows (k,) int64: only these hits, in this order."""
        if rows is None:
            rows = np.arange(len(inst))
        bad, p, ng, ns, albedo, emission, p_err = shade_kernels.surface(
            np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(inst, np.int32),
            np.ascontiguousarray(prim, np.int32),
            np.ascontiguousarray(u, np.float32), np.ascontiguousarray(v, np.float32),
            np.ascontiguousarray(direction, np.float32), self.slot_of_mesh, self.inst_mesh,
            self.l2w, self.nmat, self.verts, self.faces,
            self.normals, self.uvs, self.vbase, self.fbase, self.has_n, self.has_uv,
            self.mesh_mat, self.mat_albedo, self.mat_emission, self.mat_tex, self.tex_base,
            self.tex_h, self.tex_w, self.texels, self.w2l)
        if bad >= 0:
            m = int(self.inst_mesh[inst[bad]])  # bad: an index into inst
            raise KeyError(f"mesh {m} of instance {int(inst[bad])} is not held here "
                           f"(held: {self.held})")
        return Surface(p, ng, ns, albedo, emission, p_err)


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
