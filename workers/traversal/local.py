"""Two-level intersection over a set of instances: top-level boxes, then Embree on the
base mesh with rays moved into local space. A shard holds one of these for its own
instances; the reference renderer holds one for all of them."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import pairs as kernels
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.batch import precedes
from nprt.workers.wavefront.lights import FAR_T

# Instance boxes are culled at tmax stretched by this much (256 float32 ulps): the float32
# t Embree gives a hit may round below its box's float64 entry distance, and a hit tied
# with tmax must still be found for the tie rule. Hits themselves are cut at tmax exactly.
BOX_TMAX_SLACK_REL = 2.0**-16
# Crossings are traced in rounds, each ray's nearest box first, so a hit found in one round
# culls the boxes it hides in the next (their entry lies beyond it). Rounds take ranks
# [ROUNDS[j], ROUNDS[j + 1]); the last takes the rest. More rounds mean more, smaller
# Embree calls.
ROUNDS = (0, 1, 2)


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

    def _crossings(self, origin, direction, box_tmax):
        """Box crossings ray (p,) int64, inst (p,) int32, t_enter (p,) float64, their
        rank within their ray (nearest first), and origin, direction as float64 C arrays."""
        ray, inst, t_enter, _ = self.table.box_entries(origin, direction, box_tmax,
                                                       self.instances)
        o = np.ascontiguousarray(origin, np.float64)
        d = np.ascontiguousarray(direction, np.float64)
        return ray, inst, t_enter, kernels.entry_rank(ray, t_enter), o, d

    def _rounds(self, rank):
        top = int(rank.max()) + 1 if len(rank) else 0
        bounds = [k for k in ROUNDS if k < top] + [max(top, 1)]
        return list(zip(bounds[:-1], bounds[1:], strict=True))

    def intersect_closest(self, origin: np.ndarray, direction: np.ndarray, tmax: np.ndarray,
                          hit_inst: np.ndarray | None = None,
                          hit_prim: np.ndarray | None = None):
        """Closest hit among these instances within (0, tmax), or, given the record a ray
        carries (hit_inst, hit_prim (n,) int32 at t = tmax), the hit that precedes it in
        the global order (`nprt.workers.wavefront.batch.precedes`: a hit at t == tmax
        replaces the record when its instance ranks lower), so folding shard by shard in
        any order gives the same hit as one fold over every instance.

        origin (n, 3) float64 world, direction (n, 3) float32 world; tmax : (n,) float32
        returns t (n,) float32 (tmax where no hit), inst (n,) int32 (-1), prim (n,) int32,
        u, v (n,) float32
        """
        n = len(origin)
        tmax = np.ascontiguousarray(tmax, np.float32)
        # Each ray's closest candidate so far: smaller t, then the lower instance (an
        # instance gives a ray one hit, so (t, inst) orders them totally).
        run_t = np.full(n, np.inf, np.float32)
        run_inst = np.full(n, -1, np.int32)
        run_prim = np.full(n, -1, np.int32)
        run_u, run_v = np.zeros(n, np.float32), np.zeros(n, np.float32)
        cut = tmax.copy()  # (n,) float32 no crossing entered beyond this can win
        ray, inst, t_enter, rank, o, d = self._crossings(
            origin, direction, tmax.astype(np.float64) * (1.0 + BOX_TMAX_SLACK_REL))
        mesh_of, n_mesh, w2l = self.table.kernel_arrays()
        for k_lo, k_hi in self._rounds(rank):
            r, i, start, lo, ld = kernels.closest_round(
                ray, inst, rank, t_enter, k_lo, k_hi, cut, BOX_TMAX_SLACK_REL, mesh_of,
                n_mesh, w2l, o, d)
            for m in np.flatnonzero(start[1:] > start[:-1]):
                a, b = start[m], start[m + 1]
                # Embree gets tfar = FAR_T, not the cut: which of two triangles tied on a
                # shared edge it reports depends on tfar, and an exact render must not
                # depend on the tmax a ray happened to arrive with (nor on which shard found
                # the closer hit). Crossings are culled by box entry instead, which is exact.
                t, prim, u, v = self.geometry[m].closest_into(
                    lo[a:b], ld[a:b], np.full(b - a, FAR_T, np.float32))
                kernels.fold_closest(r[a:b], i[a:b], t, prim, u, v, tmax, run_t, run_inst,
                                     run_prim, run_u, run_v, cut)
        t_best = tmax.copy()
        if hit_inst is None:
            better = (run_inst >= 0) & (run_t < t_best)
        else:
            better = (run_inst >= 0) & precedes(run_t, run_inst, run_prim, t_best, hit_inst,
                                                hit_prim)
        t_best[better] = run_t[better]
        inst_best = np.where(better, run_inst, -1).astype(np.int32)
        prim_best = np.where(better, run_prim, -1).astype(np.int32)
        u_best = np.where(better, run_u, np.float32(0)).astype(np.float32)
        v_best = np.where(better, run_v, np.float32(0)).astype(np.float32)
        return t_best, inst_best, prim_best, u_best, v_best

    def intersect_occluded(self, origin: np.ndarray, direction: np.ndarray,
                           tmax: np.ndarray) -> np.ndarray:
        """(n,) bool: some instance here blocks the segment (0, tmax). Shapes as above."""
        tmax = np.ascontiguousarray(tmax, np.float32)
        occluded = np.zeros(len(origin), bool)
        ray, inst, _, rank, o, d = self._crossings(origin, direction, tmax)
        mesh_of, n_mesh, w2l = self.table.kernel_arrays()
        for k_lo, k_hi in self._rounds(rank):
            r, _, start, lo, ld = kernels.occluded_round(
                ray, inst, rank, k_lo, k_hi, occluded, mesh_of, n_mesh, w2l, o, d)
            for m in np.flatnonzero(start[1:] > start[:-1]):
                a, b = start[m], start[m + 1]
                rr = r[a:b]
                hit = self.geometry[m].occluded_into(lo[a:b], ld[a:b], tmax[rr])
                occluded[rr[hit]] = True  # not |=: rr repeats when a ray meets two instances
        return occluded
