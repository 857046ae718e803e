"""Where a ray goes next (the traversal policies). Each function takes rays that have
been intersected against this shard's geometry and returns a target per ray: a shard
id, or DONE (finish here: shade, or add the shadow contribution)."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import owned
from nprt.workers.kernels.nearest import NONE as NO_OWNER
from nprt.workers.kernels.nearest import nearest_owner
from nprt.workers.runtime.protocol import EVERYWHERE
from nprt.workers.traversal.local import BOX_TMAX_SLACK_REL, NearestRemote
from nprt.workers.wavefront.batch import RayBatch, ShadowRayBatch
from nprt.workers.wavefront.world import ShardWorld

DONE = -1


def visited_bit(shard: int) -> np.uint64:
    return np.uint64(1) << np.uint64(shard)


def first_of_runs(key: np.ndarray) -> np.ndarray:
    """(n,) bool: the first row of each run of equal `key` (n,) in a sorted array; after a
    lexsort whose last key is the ray, the best candidate of each ray."""
    first = np.ones(len(key), bool)
    first[1:] = key[1:] != key[:-1]
    return first


def hit_owner(world: ShardWorld, inst: np.ndarray) -> np.ndarray:
    """(n,) int32 shard owning each hit instance (n,) int32; EVERYWHERE for a replicated mesh
    and for no hit (-1)."""
    return np.where(inst >= 0, world.owner[np.maximum(inst, 0)], EVERYWHERE).astype(np.int32)


def nearest_unvisited(world: ShardWorld, remote: np.ndarray, origin, direction, tmax,
                      visited: np.ndarray, route_in: tuple | None = None) -> np.ndarray:
    """Wald-style step: the owner of the nearest box entry, among instances on shards
    this ray has not visited, that lies before tmax (ties to the lowest owner), by a walk
    of its own (the exact policy's shards have it from their local walks instead:
    `next_stop`).

    remote : (m,) int32 instances not intersected here; visited : (n,) uint64 bitmask;
    route_in: `world.table.route_inputs(candidate_owner(world, remote))`, when the caller
    keeps it
    returns (n,) int32 target shard or DONE
    """
    if not len(origin):
        return np.zeros(0, np.int32)
    # Stretched as local intersection culls (nprt.workers.traversal.local): a hit on another
    # shard tied with tmax must still be visited, or the global tie rule could not see it.
    box_tmax = np.asarray(tmax, np.float64) * (1.0 + BOX_TMAX_SLACK_REL)
    # Directions as the batches carry them, float32 (the search takes 1 / d in float64
    # either way): the walks pass the same types, so `near_search` compiles once, not
    # twice (about 6.5 s of a cold compile).
    owner = nearest_owner(
        owned(origin, np.float64), owned(direction, np.float32), owned(box_tmax, np.float64),
        *world.table.search_arrays(),
        *(route_in or world.table.route_inputs(candidate_owner(world, remote))),
        owned(visited, np.uint64))
    return np.where(owner == NO_OWNER, DONE, owner).astype(np.int32)


def candidate_owner(world: ShardWorld, remote: np.ndarray) -> np.ndarray:
    """(m,) int32: the owner of each instance of remote (m,) int32, -1 for the others: the
    boxes a routing walk (`LocalGeometry.closest_routed`) may pick as the next stop."""
    cand = np.full(len(world.table), -1, np.int32)
    cand[remote] = world.owner[remote]
    return cand


def next_stop(near: NearestRemote, tmax: np.ndarray) -> np.ndarray:
    """`nearest_unvisited` from what the routing walk kept, cut at the final tmax (n,)
    float32, which must be at most near.walk_tmax (`_routed` asks again where not).

    Why it is the same answer: after tracing its local boxes, the walk kept the nearest
    candidate crossed before C' = C * (1 + BOX_TMAX_SLACK_REL), C its cut (the closest
    hit here, or the tmax the ray came with). The final tmax T <= C (the quad lights may
    shorten it further), so the boxes crossed before T' = T * (1 + BOX_TMAX_SLACK_REL)
    are among those (the slab test depends on tmax only through t_enter < tmax): if the
    walk's candidate is entered before T', it is their nearest, with the same lowest
    owner on equal entries; if not, none of them is entered before T'.
    returns (n,) int32 target shard or DONE"""
    box_tmax = np.asarray(tmax, np.float64) * (1.0 + BOX_TMAX_SLACK_REL)
    return np.where(near.t_enter < box_tmax, near.owner, DONE).astype(np.int32)


def _routed(world, remote, origin, direction, tmax, visited, near, route_in=None
            ) -> np.ndarray:
    """nearest_unvisited, from the walk's answer where there is one."""
    if near is None:
        return nearest_unvisited(world, remote, origin, direction, tmax, visited, route_in)
    target = next_stop(near, tmax)
    # A tmax that grew after the walk (never, as hits only shorten it) is asked again.
    stale = np.flatnonzero(~(np.asarray(tmax, np.float32) <= near.walk_tmax)
                           & ~(np.isnan(tmax) & np.isnan(near.walk_tmax)))
    if len(stale):
        target[stale] = nearest_unvisited(world, remote, origin[stale], direction[stale],
                                          tmax[stale], visited[stale])
    return target


def route_exact(world: ShardWorld, shard: int, remote: np.ndarray, rays: RayBatch,
                near: NearestRemote | None = None, route_in: tuple | None = None
                ) -> np.ndarray:
    """Closest-hit rays: forward until no unvisited box lies before the hit, then go to
    the shard that owns the hit to be shaded. near: the routing walk's answer for these
    rays (`LocalGeometry.closest_routed` with `candidate_owner(world, remote)`); without
    it the top level is walked again (route_in: as in `nearest_unvisited`)."""
    target = _routed(world, remote, rays.origin, rays.direction, rays.tmax, rays.visited, near,
                     route_in)
    return _to_owner(world, shard, target, rays.hit_inst)


def route_exact_rows(world: ShardWorld, shard: int, remote: np.ndarray, rays: RayBatch,
                     rows: np.ndarray, route_in: tuple | None = None) -> np.ndarray:
    """`route_exact(rays.take(rows))` without the copy of the whole batch: rows (r,) int64;
    the top level is walked again. Returns (r,) int32."""
    target = nearest_unvisited(world, remote, rays.origin[rows], rays.direction[rows],
                               rays.tmax[rows], rays.visited[rows], route_in)
    return _to_owner(world, shard, target, rays.hit_inst[rows])


def _to_owner(world, shard, target, hit_inst):
    """target (n,) int32 of the routing step, with rays that end (DONE) sent on to the
    shard owning their hit hit_inst (n,) int32 where that is another one."""
    done = target == DONE
    owner = hit_owner(world, hit_inst)
    elsewhere = done & (owner != EVERYWHERE) & (owner != shard)
    target[elsewhere] = owner[elsewhere]
    return target


def route_shadow_exact(world: ShardWorld, remote: np.ndarray, shadow: ShadowRayBatch,
                       near: NearestRemote | None = None, route_in: tuple | None = None):
    """Unoccluded-so-far shadow rays: forward to the next unvisited box's shard. near,
    route_in: as in `route_exact` (`LocalGeometry.occluded_routed`)."""
    return _routed(world, remote, shadow.origin, shadow.direction, shadow.tmax,
                   shadow.visited, near, route_in)
