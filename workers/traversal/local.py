"""Two-level intersection over a set of instances: top-level boxes, then Embree on the
base mesh with rays moved into local space. A shard holds one of these for its own
instances; the reference renderer holds one for all of them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nprt.workers.kernels import crossings, records
from nprt.workers.traversal import rtc
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.planar import plane_rows
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.lights import FAR_T

# Instance boxes are culled at tmax stretched by this much (256 float32 ulps): the float32
# t Embree gives a hit may round below its box's float64 entry distance, and a hit tied
# with tmax must still be found for the tie rule. Hits themselves are cut at tmax exactly.
BOX_TMAX_SLACK_REL = 2.0**-16


def _walk_direction(direction) -> np.ndarray:
    """direction (n, 3) as the walks take it: float32 (a RayBatch's) as it is, anything
    else as float64. The kernels widen each component to float64 before any arithmetic,
    so both give the same bits; the float32 path saves a converted copy a batch."""
    d = np.asarray(direction)
    return np.ascontiguousarray(d, np.float32 if d.dtype == np.float32 else np.float64)


@dataclass(frozen=True, eq=False)
class NearestRemote:
    """What a routing walk (`LocalGeometry.closest_routed`, `occluded_routed`) found for
    exact forwarding, before the final tmax cuts it: per ray, t_enter (n,) float64, the
    nearest entry of a candidate box on a shard the ray had not visited, crossed before
    walk_tmax (n,) float32 (the walk's cut: its closest hit here, or the tmax it came
    with) stretched by BOX_TMAX_SLACK_REL (inf: none), and owner (n,) int32 its shard
    (-1: none; on equal entries the lowest)."""

    t_enter: np.ndarray
    owner: np.ndarray
    walk_tmax: np.ndarray

    def take(self, index: np.ndarray) -> NearestRemote:
        return NearestRemote(self.t_enter[index], self.owner[index], self.walk_tmax[index])


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
        self._scene_of_mesh = None
        self._planes = None
        self._walk_inputs = None
        self._routed = None  # (cand_owner, its route inputs)
        self._no_route = None

    def __repr__(self) -> str:
        return f"LocalGeometry({len(self.geometry)} meshes, {len(self.instances)} instances)"

    def _walk(self) -> tuple:
        """The top-level inputs of the walking kernels for these instances (made once)."""
        if self._walk_inputs is None:
            self._walk_inputs = self.table.walk_inputs(self.instances)
        return self._walk_inputs

    def _route(self, cand_owner: np.ndarray) -> tuple:
        """The routing search's inputs for cand_owner (m,) int32 (`InstanceTable.
        route_inputs`), made once for the last array passed (a policy keeps one)."""
        if self._routed is None or self._routed[0] is not cand_owner:
            self._routed = (cand_owner, self.table.route_inputs(cand_owner))
        return self._routed[1]

    def _route_args(self, n: int, cand_owner, visited) -> tuple:
        """The walking kernels' routing arguments: (route, cand_owner, cands, cand_flat,
        cand_bvh, visited (n,) uint64, near_t (n,) float64, near_owner (n,) int32,
        near_tmax (n,) float32); placeholders when they do not route."""
        if cand_owner is None:
            if self._no_route is None:  # never written: made once
                cand, cands, cand_flat, _ = self.table.route_inputs(
                    np.full(len(self.table), -1, np.int32))
                self._no_route = (False, cand, cands, cand_flat, False, np.zeros(0, np.uint64),
                                  np.zeros(0), np.zeros(0, np.int32), np.zeros(0, np.float32))
            return self._no_route
        seen = np.ascontiguousarray(visited, np.uint64)
        if seen.shape != (n,):
            raise ValueError(f"visited must have shape ({n},), got {seen.shape}")
        return (True, *self._route(cand_owner), seen, np.full(n, np.inf),
                np.full(n, -1, np.int32), np.empty(n, np.float32))

    def _scenes(self) -> np.ndarray:
        """(M,) uint64 Embree scene of each base mesh held here (0 elsewhere)."""
        if self._scene_of_mesh is None:
            n = max(self.table.n_mesh, max(self.geometry, default=-1) + 1)
            scenes = np.zeros(n, np.uint64)
            for m, g in self.geometry.items():
                scenes[m] = g.rtc.handle
            self._scene_of_mesh = scenes
        return self._scene_of_mesh

    def _mesh_planes(self) -> np.ndarray:
        """(M, 3) float64 `plane_rows` of the base meshes held here (made once)."""
        if self._planes is None:
            self._planes = plane_rows({m: (g.mesh.vertices, g.mesh.faces)
                                       for m, g in self.geometry.items()},
                                      len(self._scenes()))
        return self._planes

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
        return self._closest(origin, direction, tmax, hit_inst, hit_prim, None, None)[:5]

    def closest_routed(self, origin, direction, tmax, hit_inst, hit_prim,
                       cand_owner: np.ndarray, visited: np.ndarray):
        """`intersect_closest` and, from the same walk of the top level, exact forwarding's
        next stop (`NearestRemote`) among the boxes of cand_owner (m,) int32 (the owner of
        each box it may visit next, -1 elsewhere) on shards not in visited (n,) uint64.
        Returns t, inst, prim, u, v, NearestRemote."""
        return self._closest(origin, direction, tmax, hit_inst, hit_prim, cand_owner,
                             visited)

    def _closest(self, origin, direction, tmax, hit_inst, hit_prim, cand_owner, visited):
        n = len(origin)
        tmax = np.ascontiguousarray(tmax, np.float32)
        # Each ray's closest candidate so far: smaller t, then the lower instance (an
        # instance gives a ray one hit, so (t, inst) orders them totally).
        run_t = np.full(n, np.inf, np.float32)
        run_inst = np.full(n, -1, np.int32)
        run_prim = np.full(n, -1, np.int32)
        run_u, run_v = np.zeros(n, np.float32), np.zeros(n, np.float32)
        o = np.ascontiguousarray(origin, np.float64)
        d = _walk_direction(direction)
        mesh_of, _, w2l = self.table.kernel_arrays()
        route = self._route_args(n, cand_owner, visited)
        # Each ray walks the top level nearest box first and traces each box it reaches
        # until boxes are entered beyond its closest hit so far (exact: no hit there can
        # win or tie). Embree gets tfar = that hit's t (or tmax) stretched by
        # crossings.TFAR_MARGIN_REL, not the t itself: with tfar == t, which of two
        # triangles tied on a shared edge it reports may change, and an exact render must
        # not depend on the tmax a ray arrived with (nor on which shard found the closer
        # hit). With the margin it reports what it reports with tfar = FAR_T (see
        # crossings._closest_box, tests/workers/test_rtc.py).
        crossings.closest_walk(np.uint64(rtc.INTERSECT1), o, d, tmax, BOX_TMAX_SLACK_REL, FAR_T,
                               *self._walk(), mesh_of, self._scenes(), self._mesh_planes(), w2l,
                               run_t, run_inst, run_prim, run_u, run_v, *route)
        use_record = hit_inst is not None
        if not use_record:
            hit_inst = hit_prim = np.zeros(n, np.int32)
        out = records.local_winners(run_t, run_inst, run_prim, run_u, run_v, tmax,
                                    np.ascontiguousarray(hit_inst, np.int32),
                                    np.ascontiguousarray(hit_prim, np.int32), use_record)
        return (*out, NearestRemote(*route[-3:]) if route[0] else None)

    def intersect_occluded(self, origin: np.ndarray, direction: np.ndarray,
                           tmax: np.ndarray) -> np.ndarray:
        """(n,) bool: some instance here blocks the segment (0, tmax). Shapes as above."""
        return self._occluded(origin, direction, tmax, None, None)[0]

    def occluded_routed(self, origin, direction, tmax, cand_owner: np.ndarray,
                        visited: np.ndarray):
        """`intersect_occluded` and, from the same walk, exact forwarding's next stop for
        the rays not occluded here (as `closest_routed`; meaningless for occluded rays).
        Returns occluded (n,) bool, NearestRemote."""
        return self._occluded(origin, direction, tmax, cand_owner, visited)

    def _occluded(self, origin, direction, tmax, cand_owner, visited):
        n = len(origin)
        tmax = np.ascontiguousarray(tmax, np.float32)
        occluded = np.zeros(n, bool)
        o = np.ascontiguousarray(origin, np.float64)
        d = _walk_direction(direction)
        mesh_of, _, w2l = self.table.kernel_arrays()
        route = self._route_args(n, cand_owner, visited)
        crossings.occluded_walk(np.uint64(rtc.OCCLUDED1), o, d, tmax, BOX_TMAX_SLACK_REL,
                                *self._walk(), mesh_of, self._scenes(), self._mesh_planes(),
                                w2l, occluded, *route[:-1])
        return occluded, NearestRemote(*route[-3:-1], tmax) if route[0] else None
