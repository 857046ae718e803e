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
        self._rtc = None

    @property
    def rtc(self):
        """The same triangles as an `nprt.workers.traversal.rtc.RtcScene` (built on first
        use), for compiled loops that trace a ray through several instances."""
        if self._rtc is None:
            from nprt.workers.traversal.rtc import RtcScene

            self._rtc = RtcScene(self.mesh.vertices, self.mesh.faces)
        return self._rtc

    def __repr__(self) -> str:
        return f"MeshGeometry({self.mesh.name!r}, {len(self.mesh.faces)} triangles)"

    def intersect_closest(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray):
        """Closest hit within (0, tmax).

        origin, direction : (n, 3) float32, local space (direction need not be unit)
        tmax : (n,) float32
        returns t (n,) float32 (inf where no hit), prim (n,) int32 (-1), u, v (n,) float32
        """
        if len(origin) == 0:
            z = np.zeros(0, np.float32)
            return z, np.zeros(0, np.int32), z, z
        # A copy: embreex writes each hit's tfar back into `dists` in place.
        t, prim, u, v = self.closest_into(np.ascontiguousarray(origin, dtype=EMBREE_DTYPE),
                                          np.ascontiguousarray(direction, dtype=EMBREE_DTYPE),
                                          np.array(tmax, dtype=EMBREE_DTYPE))
        return np.where(prim >= 0, t, _NO_HIT_T).astype(np.float32), prim, u, v

    def closest_into(self, origin: np.ndarray, direction: np.ndarray, tfar: np.ndarray):
        """`intersect_closest` without copies, for the traversal's own buffers: origin,
        direction (n, 3) float32 C-contiguous; tfar (n,) float32, overwritten with each
        hit's t (unchanged where prim is -1). Returns tfar, prim, u, v as Embree wrote them."""
        r = self._scene.run(origin, direction, dists=tfar, output=1)
        return r["tfar"], r["primID"], r["u"], r["v"]

    def intersect_occluded(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray):
        """Any hit within (0, tmax). Shapes as intersect_closest; returns (n,) bool."""
        if len(origin) == 0:
            return np.zeros(0, bool)
        return self.occluded_into(np.ascontiguousarray(origin, dtype=EMBREE_DTYPE),
                                  np.ascontiguousarray(direction, dtype=EMBREE_DTYPE),
                                  np.array(tmax, dtype=EMBREE_DTYPE))

    def occluded_into(self, origin: np.ndarray, direction: np.ndarray,
                      tmax: np.ndarray) -> np.ndarray:
        """`intersect_occluded` without copies: tmax (n,) float32 is the caller's to lose
        (embreex may write it)."""
        return np.asarray(self._scene.run(origin, direction, dists=tmax,
                                          query="OCCLUDED")) >= 0
