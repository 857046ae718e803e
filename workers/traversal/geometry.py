"""Embree over one base mesh in its local space: the bottom level of the two-level BVH.

embreex fixes tnear at 0, so callers offset origins (nprt.workers.kernels.offset) before tracing.
"""

from __future__ import annotations

import numpy as np
from embreex import mesh_construction, rtcore_scene

from nprt.scene.model import Mesh

EMBREE_DTYPE = np.float32
_NO_HIT_T = np.float32(np.inf)


class MeshGeometry:
    """Closest-hit and occlusion queries against one base mesh (local space)."""

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        # Robust mode: watertight traversal, so rays do not slip between shared edges.
        self._scene = rtcore_scene.EmbreeScene(robust=True)
        mesh_construction.TriangleMesh(
            self._scene,
            np.ascontiguousarray(mesh.vertices, dtype=EMBREE_DTYPE),
            np.ascontiguousarray(mesh.faces, dtype=np.int32),
        )

    def __repr__(self) -> str:
        return f"MeshGeometry({self.mesh.name!r}, {len(self.mesh.faces)} triangles)"

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 local AABB."""
        return self.mesh.bounds

    def intersect_closest(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray):
        """Closest hit within (0, tmax).

        origin, direction : (n, 3) float32, local space (direction need not be unit)
        tmax : (n,) float32
        returns t (n,) float32 (inf where no hit), prim (n,) int32 (-1), u, v (n,) float32
        """
        if len(origin) == 0:
            z = np.zeros(0, np.float32)
            return z, np.zeros(0, np.int32), z, z
        r = self._scene.run(
            np.ascontiguousarray(origin, dtype=EMBREE_DTYPE),
            np.ascontiguousarray(direction, dtype=EMBREE_DTYPE),
            # A copy: embreex writes each hit's tfar back into `dists` in place.
            dists=np.array(tmax, dtype=EMBREE_DTYPE),
            output=1,
        )
        prim = r["primID"].astype(np.int32)
        t = np.where(prim >= 0, r["tfar"], _NO_HIT_T).astype(np.float32)
        return t, prim, r["u"].astype(np.float32), r["v"].astype(np.float32)

    def intersect_occluded(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray):
        """Any hit within (0, tmax). Shapes as intersect_closest; returns (n,) bool."""
        if len(origin) == 0:
            return np.zeros(0, bool)
        r = self._scene.run(
            np.ascontiguousarray(origin, dtype=EMBREE_DTYPE),
            np.ascontiguousarray(direction, dtype=EMBREE_DTYPE),
            dists=np.array(tmax, dtype=EMBREE_DTYPE),  # copy: embreex writes tfar in place
            query="OCCLUDED",
        )
        return np.asarray(r) >= 0
