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
        """The surfaces of hits through the kernel (bit-identical to the oracle
        `surface_at` in tests/workers/oracles.py); the same arguments, and
        optionally rows (k,) int64: only these hits, in this order."""
        if rows is None:
            rows = np.arange(len(inst))
        bad, p, ng, ns, albedo, emission, p_err = shade_kernels.surface(
            np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(inst, np.int32),
            np.ascontiguousarray(prim, np.int32),
            np.ascontiguousarray(u, np.float32), np.ascontiguousarray(v, np.float32),
            np.ascontiguousarray(direction, np.float32), *self.kernel_tables())
        if bad >= 0:
            self.refuse(int(inst[bad]))  # bad: an index into inst
        return Surface(p, ng, ns, albedo, emission, p_err)

    def kernel_tables(self) -> tuple:
        """The tables in the order the kernels take them (`shade_kernels.surface`'s
        arguments after direction)."""
        made = self.__dict__.get("_kernel_tables")
        if made is None:
            made = self._kernel_tables = (
                self.slot_of_mesh, self.inst_mesh, self.l2w, self.nmat, self.verts,
                self.faces, self.normals, self.uvs, self.vbase, self.fbase, self.has_n,
                self.has_uv, self.mesh_mat, self.mat_albedo, self.mat_emission, self.mat_tex,
                self.tex_base, self.tex_h, self.tex_w, self.texels, self.w2l)
        return made

    def refuse(self, inst: int):
        """Raise the error of a hit on instance `inst`, whose mesh is not held here."""
        m = int(self.inst_mesh[inst])
        raise KeyError(f"mesh {m} of instance {inst} is not held here (held: {self.held})")
