"""Two-level intersection over a set of instances: top-level boxes, then Embree on the
base mesh with rays moved into local space. A shard holds one of these for its own
instances; the reference renderer holds one for all of them."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import bvh as kernels
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.batch import precedes

_FAR = np.float32(1e30)
# Instance boxes are culled at tmax stretched by this much (256 float32 ulps): the float32
# t Embree gives a hit may round below its box's float64 entry distance, and a hit tied
# with tmax must still be found for the tie rule. Hits themselves are cut at tmax exactly.
BOX_TMAX_SLACK_REL = 2.0**-16


class LocalGeometry:
    """geometry : {mesh index: MeshGeometry} for the meshes held here;
    instances : (k,) int32 instance indices intersected here."""

    def __init__(self, geometry: dict[int, MeshGeometry], table: InstanceTable,
                 instances: np.ndarray):
        self.geometry, self.table = geometry, table
        self.instances = np.asarray(instances, np.int32)
        missing = set(table.mesh[self.instances].tolist()) - set(geometry)
        if missing:
            raise ValueError(f"instances reference meshes {sorted(missing)} not held here")

    def __repr__(self) -> str:
        return f"LocalGeometry({len(self.geometry)} meshes, {len(self.instances)} instances)"

    def _pairs_by_mesh(self, origin, direction, tmax):
        """Yield (mesh index, ray (p,) int64, inst (p,) int32, local origin/direction), by
        ascending mesh, crossings in `box_entries` order within a mesh."""
        ray, inst, _, _ = self.table.box_entries(origin, direction, tmax, self.instances)
        if len(ray) == 0:
            return
        ray, inst, start, lo, ld = self.table.pairs_by_mesh(ray, inst, origin, direction)
        for m in np.flatnonzero(start[1:] > start[:-1]):
            a, b = start[m], start[m + 1]
            yield int(m), ray[a:b], inst[a:b], lo[a:b], ld[a:b]

    def intersect_closest(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray,
                          hit_inst: np.ndarray | None = None,
                          hit_prim: np.ndarray | None = None):
        """Closest hit among these instances within (0, tmax), or, given the record a ray
        carries (hit_inst, hit_prim (n,) int32 at t = tmax), the hit that precedes it in
        the global order (`nprt.workers.wavefront.batch.precedes`: a hit at t == tmax replaces the
        record when its instance ranks lower), so folding shard by shard in any order
        gives the same hit as one fold over every instance.

        origin (n, 3) float64 world, direction (n, 3) float32 world; tmax : (n,) float32
        returns t (n,) float32 (tmax where no hit), inst (n,) int32 (-1), prim (n,) int32,
        u, v (n,) float32
        """
        n = len(origin)
        t_best = tmax.astype(np.float32).copy()
        inst_best = np.full(n, -1, np.int32)
        prim_best = np.full(n, -1, np.int32)
        u_best = np.zeros(n, np.float32)
        v_best = np.zeros(n, np.float32)
        # Each ray's closest candidate so far: smaller t, then the lower instance (an
        # instance gives a ray one hit, so (t, inst) orders them totally). Folded in per
        # mesh (a jitted loop, no sort of all hits).
        run_t = np.full(n, np.inf, np.float32)
        run_inst = np.full(n, -1, np.int32)
        run_prim = np.full(n, -1, np.int32)
        run_u, run_v = np.zeros(n, np.float32), np.zeros(n, np.float32)
        box_tmax = tmax.astype(np.float64) * (1.0 + BOX_TMAX_SLACK_REL)
        for m, r, i, lo, ld in self._pairs_by_mesh(origin, direction, box_tmax):
            # Embree always gets tfar = inf: which of two triangles tied on a shared edge
            # it reports depends on tfar, and an exact render must not depend on the
            # tmax a ray happened to arrive with. The tmax cut is applied here instead.
            far = np.full(len(r), _FAR, np.float32)  # fresh: embreex writes tfar in place
            t, prim, u, v = self.geometry[m].intersect_closest(lo, ld, far)
            hit = (prim >= 0) & (t <= tmax[r])  # t == tmax: the record decides below
            kernels.closest_candidates(
                r[hit], t[hit], i[hit], prim[hit], u[hit], v[hit],
                run_t, run_inst, run_prim, run_u, run_v)
        if hit_inst is None:
            better = (run_inst >= 0) & (run_t < t_best)
        else:
            better = (run_inst >= 0) & precedes(run_t, run_inst, run_prim, t_best, hit_inst,
                                                hit_prim)
        t_best[better], inst_best[better] = run_t[better], run_inst[better]
        prim_best[better] = run_prim[better]
        u_best[better], v_best[better] = run_u[better], run_v[better]
        return t_best, inst_best, prim_best, u_best, v_best

    def intersect_occluded(self, origin: np.ndarray, direction: np.ndarray,
                           tmax: np.ndarray) -> np.ndarray:
        """(n,) bool: some instance here blocks the segment (0, tmax). Shapes as above."""
        occluded = np.zeros(len(origin), bool)
        for m, r, _, lo, ld in self._pairs_by_mesh(origin, direction, tmax):
            live = ~occluded[r]
            if live.any():
                r = r[live]
                hit = self.geometry[m].intersect_occluded(lo[live], ld[live], tmax[r])
                occluded[r[hit]] = True  # not |=: r repeats when a ray meets two instances
        return occluded
