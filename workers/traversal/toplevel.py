"""The instance table: world boxes and float64 transforms of every instance, replicated
on every shard, with a small BVH over the boxes (the top level) and the slab test."""

from __future__ import annotations

import numpy as np

from nprt.scene.model import Scene
from nprt.workers.kernels import bvh as kernels

# Boxes are padded so flat geometry (a ground quad) never yields a zero-width slab: by
# BOX_PAD_REL of their diagonal, BOX_PAD_ABS (a box of one point), and BOX_PAD_COORD_REL
# of their largest |coordinate| (float32 vertices far from the origin round by that much).
BOX_PAD_REL = 1e-5
BOX_PAD_ABS = 1e-9
BOX_PAD_COORD_REL = 1e-7
# Up to this many requested instances, a plain loop over their boxes beats the BVH.
BVH_MIN_INSTANCES = 8
# The walking kernels test up to this many boxes a ray in one flat loop (vectorised)
# instead of walking the BVH. Walk kernels on a render's rays, closest / occlusion s, flat
# against BVH (same process): foliage (24 boxes) 0.285 / 0.222 against 0.346 / 0.269,
# forest small (39) 0.277 / 0.065 against 0.306 / 0.078, city default (65) 0.418 / 0.107
# against 0.510 / 0.115, forest default (85) 0.602 / 0.538 against 0.575 / 0.474.
FLAT_WALK_MAX = 72
# The routing search (the nearest box on an unvisited shard, culled at the best so far)
# takes every candidate's slab in one flat loop up to this many candidates, else walks
# the BVH nearer child first. `bench_route_search` (the search alone on an exact render's
# rays, flat / BVH CPU): 0.67-0.69x with 28-49 candidates (K = 2), 0.92-0.97x with 45-71
# (K = 4), 0.91-1.10x with city's 65 boxes all candidates, 1.34x with forest's 85 (was 8,
# when the flat loop handled NaN on every box).
ROUTE_FLAT_MAX = 64


class InstanceTable:
    """mesh (m,) int32, local_to_world / world_to_local (m, 3, 4) float64,
    normal_to_world (m, 3, 3) float64 (inverse transpose), world_bounds (m, 2, 3) float64,
    local_bounds (m, 2, 3) float64 (the base mesh's box).

    Built from the scene's instance arrays in vectorised numpy plus one compiled BVH
    build; the BVH travels with the table when it is pickled (built once per scene)."""

    def __init__(self, scene: Scene):
        self.mesh = np.array(scene.instance_mesh, np.int32)
        l2w = np.array(scene.instance_transform, np.float64)  # (m, 4, 4)
        w2l = np.linalg.inv(l2w)
        self.local_to_world = l2w[:, :3, :]
        self.world_to_local = w2l[:, :3, :]
        self.normal_to_world = np.transpose(w2l[:, :3, :3], (0, 2, 1))
        mesh_bounds = np.stack([m.bounds for m in scene.meshes])  # (meshes, 2, 3)
        local = mesh_bounds[self.mesh]  # (m, 2, 3)
        corners = _box_corners(local)  # (m, 8, 3)
        world = np.einsum("mij,mkj->mki", l2w[:, :3, :3], corners) + l2w[:, None, :3, 3]
        lo, hi = world.min(axis=1), world.max(axis=1)
        pad = BOX_PAD_REL * np.linalg.norm(hi - lo, axis=1, keepdims=True) + BOX_PAD_ABS
        pad = pad + BOX_PAD_COORD_REL * np.abs(np.concatenate([lo, hi], axis=1)).max(
            axis=1, keepdims=True)
        self.world_bounds = np.stack([lo - pad, hi + pad], axis=1)
        self.local_bounds = local
        boxes = np.array(self.world_bounds, np.float64, order="C")
        bvh = kernels.bvh_build(boxes) if len(boxes) and np.isfinite(boxes).all() else None
        self._owned(bvh)

    def _owned(self, bvh) -> None:
        """Kernel inputs, owned and writable (arrays unpickled from Ray's object store are
        read-only, and numba compiles read-only arrays as a separate type). Copies only:
        the BVH is never rebuilt here."""
        self._bvh = None
        if bvh is not None:
            self._bvh = (np.array(self.world_bounds, np.float64, order="C"),
                         *(np.array(a, order="C") for a in bvh))
        self._mesh = np.array(self.mesh, np.int32)
        self._n_mesh = int(self._mesh.max()) + 1 if len(self._mesh) else 0
        self._world_to_local = np.array(self.world_to_local, np.float64, order="C")
        self._local_bounds = np.array(self.local_bounds, np.float64, order="C")
        self._member_sets: dict[bytes, tuple] = {}

    @property
    def n_mesh(self) -> int:
        """One more than the largest base mesh index of any instance (0 for none)."""
        return self._n_mesh

    def kernel_arrays(self) -> tuple[np.ndarray, int, np.ndarray]:
        """What the pair kernels (`nprt.workers.kernels.pairs`) read: mesh of each instance
        (m,) int32, the mesh count, world_to_local (m, 3, 4) float64; owned and writable."""
        return self._mesh, self.n_mesh, self._world_to_local

    @property
    def bvh(self) -> tuple | None:
        """`kernels.bvh_build(world_bounds)`'s arrays, or None (no boxes, or non-finite)."""
        return None if self._bvh is None else self._bvh[1:]

    @property
    def bvh_inputs(self) -> tuple | None:
        """(world_bounds (m, 2, 3) float64, *bvh) as the kernels take them, or None."""
        return self._bvh

    def __getstate__(self):
        state = self.__dict__.copy()
        for name in ("_bvh", "_mesh", "_n_mesh", "_world_to_local", "_local_bounds",
                     "_member_sets", "normal_to_world"):
            state.pop(name, None)  # derived from other fields, restored on unpickling
        state["bvh"] = self.bvh
        return state

    def __setstate__(self, state):
        bvh = state.pop("bvh", None)
        self.__dict__.update(state)
        self.normal_to_world = np.transpose(self.world_to_local[:, :, :3], (0, 2, 1))
        self._owned(bvh)

    def __len__(self) -> int:
        return len(self.mesh)

    def _columns(self, instances: np.ndarray) -> np.ndarray | None:
        """col_of (m,) int32: each instance's position in `instances` (-1: not there), when
        the BVH serves them (a table with a BVH, more than BVH_MIN_INSTANCES valid, unique
        instances); None: test every box instead."""
        k, m = len(instances), len(self)
        if self._bvh is None or k <= BVH_MIN_INSTANCES:
            return None
        if instances.min() < 0 or instances.max() >= m:
            return None
        col_of = np.full(m, -1, np.int32)
        col_of[instances] = np.arange(k, dtype=np.int32)
        if np.count_nonzero(col_of >= 0) != k:  # repeated instances: plain loop
            return None
        return col_of

    def pair_inputs(self, instances: np.ndarray) -> tuple:
        """What `nprt.workers.routing.proxy_pairs.walk_queries` takes for a set of
        instances (k,): world boxes (m, 2, 3) float64, the BVH's arrays (placeholders
        without one), col_of (m,) int32 (empty: loop over the members instead of walking),
        members (k,) int64, world_to_local (m, 3, 4) and local_bounds (m, 2, 3) float64,
        mesh (m,) int32; owned and writable. Kept per set: a shard asks about the same
        instances at every step."""
        instances = np.asarray(instances)
        key = instances.astype(np.int64).tobytes()
        got = self._member_sets.get(key)
        if got is None:
            members = np.array(instances, np.int64)
            col_of = self._columns(members) if len(members) else None
            if col_of is None:
                boxes, bvh, col_of = self.search_arrays()[0], _no_bvh(), np.zeros(0, np.int32)
            else:
                boxes, bvh = self._bvh[0], self._bvh[1:]
            got = (boxes, bvh, col_of, members, self._world_to_local, self._local_bounds,
                   self._mesh)
            if len(self._member_sets) >= 8:  # a shard asks about one or two sets
                self._member_sets.clear()
            self._member_sets[key] = got
        return got

    def walk_inputs(self, instances: np.ndarray) -> tuple:
        """What the walking kernels (`nprt.workers.kernels.crossings.closest_walk`) take
        for a set of instances: boxes (m, 2, 3) float64 (world_bounds), members (k,) int64,
        col_of (m,) int32, use_bvh, flat (6, k) float64 (the members' boxes as rows lo x,
        y, z, hi x, y, z, for the flat loop), then the BVH's node_box, node_child,
        node_start, node_count, prim (placeholders without one; the routing search may
        walk it when the members do not); owned and writable."""
        members = np.array(instances, np.int64)
        col_of = self._columns(members)
        bounds = np.asarray(self.world_bounds, np.float64)[members]  # (k, 2, 3)
        flat = flat_rows(bounds)
        bvh = _no_bvh() if self._bvh is None else self._bvh[1:]
        if col_of is None or len(members) <= FLAT_WALK_MAX:
            boxes = np.array(self.world_bounds, np.float64, order="C")
            return (boxes, members, np.full(len(self), -1, np.int32), False, flat, *bvh)
        return (self._bvh[0], members, col_of, True, flat, *bvh)

    def search_arrays(self) -> tuple:
        """boxes (m, 2, 3) float64 and the BVH's arrays (placeholders without one), as the
        routing search (`nprt.workers.kernels.nearest.nearest_owner`) takes them."""
        if self._bvh is not None:
            return self._bvh
        return (np.array(self.world_bounds, np.float64, order="C"), *_no_bvh())

    def route_inputs(self, cand_owner: np.ndarray) -> tuple:
        """What the walking kernels take to route as well (`crossings._near_search`):
        cand_owner (m,) int32 (the owner of each box exact forwarding may visit next, -1
        for the others), cands (c,) int64 those boxes, cand_flat (6, c) float64 their
        boxes as `walk_inputs`' flat, and cand_bvh: search through the table's BVH
        (more than ROUTE_FLAT_MAX candidates) rather than the flat loop."""
        cand = np.array(cand_owner, np.int32)
        if cand.shape != (len(self),):
            raise ValueError(f"route_inputs: cand_owner must have shape ({len(self)},), got "
                             f"{cand.shape}")
        cands = np.flatnonzero(cand >= 0).astype(np.int64)
        bounds = np.asarray(self.world_bounds, np.float64)[cands]  # (c, 2, 3)
        cand_flat = flat_rows(bounds)
        return cand, cands, cand_flat, self._bvh is not None and len(cands) > ROUTE_FLAT_MAX

    def box_entries(self, origin, direction, tmax, instances: np.ndarray):
        """Slab test of rays against a set of instance boxes, in float64.

        origin (n, 3) float64, direction (n, 3) float32; tmax : (n,) float32 or float64;
        instances : (k,) int
        returns ray (p,) int64, inst (p,) int32, t_enter (p,) float64, t_exit (p,) float64
        for every crossing with t_exit >= max(t_enter, 0) and t_enter < tmax, ray-major and
        then in the order of `instances`. Per axis t = (plane - origin) * (1 / direction),
        fmin/fmax drop the NaN of 0 * inf (origin on a slab plane, zero direction).
        """
        n, k = len(origin), len(instances)
        if n == 0 or k == 0:
            e = np.zeros(0)
            return e.astype(np.int64), e.astype(np.int32), e, e
        instances = np.asarray(instances)
        # One dtype and layout, so the kernels are compiled (and cached) once.
        o, d = np.array(origin, np.float64, order="C"), np.array(direction, np.float64, order="C")
        tm = np.array(tmax, np.float64, order="C")
        col_of = self._columns(instances)
        if col_of is not None:
            ray, col, t_enter, t_exit = kernels.bvh_slab(o, d, tm, *self._bvh, col_of)
        else:
            boxes = np.array(self.world_bounds[instances], np.float64, order="C")
            ray, col, t_enter, t_exit = kernels.slab_all(o, d, tm, boxes)
        return ray, instances[col].astype(np.int32), t_enter, t_exit


def flat_rows(boxes: np.ndarray) -> np.ndarray:
    """boxes (k, 2, 3) float64 as the flat loops take them: (6, k) float64 rows lo x, y, z,
    hi x, y, z."""
    return np.ascontiguousarray(np.asarray(boxes, np.float64).reshape(len(boxes), 6).T)


def _no_bvh() -> tuple:
    """Placeholder BVH arrays (dtypes of `kernels.bvh_build`'s) for kernels told not to
    use one."""
    return (np.zeros((1, 2, 3)), np.full(1, -1, np.int32), np.zeros(1, np.int32),
            np.zeros(1, np.int32), np.zeros(0, np.int32))


def _box_corners(b: np.ndarray) -> np.ndarray:
    """(m, 2, 3) boxes -> (m, 8, 3) corners."""
    idx = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)])  # (8, 3)
    return b[:, idx, np.arange(3)]
