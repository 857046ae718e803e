"""Surface interactions from hit records: position from barycentrics (float64, local then
world), geometric and shading normals, UVs and albedo. Only meshes held here can be shaded."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from scene.model import Material, Mesh
from workers.sampling import normalize
from workers.toplevel import InstanceTable


@dataclass(frozen=True)
class Surface:
    """p (n,3) f64 world point; ng, ns (n,3) f64 unit geometric / shading normals facing
    the incoming ray; albedo (n,3) f64; emission (n,3) f64."""

    p: np.ndarray
    ng: np.ndarray
    ns: np.ndarray
    albedo: np.ndarray
    emission: np.ndarray


def surface_at(meshes: Mapping[int, Mesh], materials: Sequence[Material],
               table: InstanceTable, inst: np.ndarray, prim: np.ndarray,
               u: np.ndarray, v: np.ndarray, direction: np.ndarray) -> Surface:
    """inst, prim (n,) int32; u, v (n,) float32 barycentrics; direction (n,3) f32 incoming."""
    n = len(inst)
    p_loc = np.zeros((n, 3))
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
    p = np.einsum("nij,nj->ni", l2w[:, :, :3], p_loc) + l2w[:, :, 3]
    nmat = table.normal_to_world[inst]
    ng = normalize(np.einsum("nij,nj->ni", nmat, ng_loc))
    ns = normalize(np.einsum("nij,nj->ni", nmat, ns_loc))
    d = direction.astype(np.float64)
    # Two-sided diffuse: both normals face the side the ray came from.
    ng = np.where((np.einsum("ij,ij->i", ng, d) > 0)[:, None], -ng, ng)
    ns = np.where((np.einsum("ij,ij->i", ns, ng) < 0)[:, None], -ns, ns)
    return Surface(p, ng, ns, albedo, emission)


def _lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest texel with wrapping. texture (h, w, 3) float32, uv (n, 2) -> (n, 3) float64."""
    h, w = texture.shape[:2]
    x = np.floor(np.mod(uv[:, 0], 1.0) * w).astype(np.int64) % w
    y = np.floor(np.mod(1.0 - uv[:, 1], 1.0) * h).astype(np.int64) % h
    return texture[y, x].astype(np.float64)
