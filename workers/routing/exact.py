"""Where a ray goes next (the traversal policies). Each function takes rays that have
been intersected against this shard's geometry and returns a target per ray: a shard
id, or DONE (finish here: shade, or add the shadow contribution)."""

from __future__ import annotations

import numpy as np

from nprt.workers.runtime.protocol import EVERYWHERE
from nprt.workers.traversal.local import BOX_TMAX_SLACK_REL
from nprt.workers.wavefront.batch import RayBatch, ShadowRayBatch
from nprt.workers.wavefront.world import ShardWorld

DONE = -1


def visited_bit(shard: int) -> np.uint64:
    return np.uint64(1) << np.uint64(shard)


def nearest_unvisited(world: ShardWorld, remote: np.ndarray, origin, direction, tmax,
                      visited: np.ndarray) -> np.ndarray:
    """Wald-style step: the owner of the nearest box entry, among instances on shards
    this ray has not visited, that lies before tmax.

    remote : (m,) int32 instances not intersected here; visited : (n,) uint64 bitmask
    returns (n,) int32 target shard or DONE
    """
    target = np.full(len(origin), DONE, np.int32)
    # Stretched as local intersection culls (nprt.workers.traversal.local): a hit on another
    # shard tied
    # with tmax must still be visited, or the global tie rule could not see it.
    box_tmax = np.asarray(tmax, np.float64) * (1.0 + BOX_TMAX_SLACK_REL)
    ray, inst, t_enter, _ = world.table.box_entries(origin, direction, box_tmax, remote)
    if len(ray) == 0:
        return target
    owner = world.owner[inst]
    fresh = (visited[ray] >> owner.astype(np.uint64)) & np.uint64(1) == 0
    ray, owner, t_enter = ray[fresh], owner[fresh], t_enter[fresh]
    order = np.lexsort((owner, t_enter, ray))
    ray, owner = ray[order], owner[order]
    first = np.ones(len(ray), bool)
    first[1:] = ray[1:] != ray[:-1]
    target[ray[first]] = owner[first]
    return target


def route_exact(world: ShardWorld, shard: int, remote: np.ndarray, rays: RayBatch) -> np.ndarray:
    """Closest-hit rays: forward until no unvisited box lies before the hit, then go to
    the shard that owns the hit to be shaded."""
    target = nearest_unvisited(world, remote, rays.origin, rays.direction, rays.tmax,
                               rays.visited)
    done = target == DONE
    hit = rays.hit_inst
    owner = np.where(hit >= 0, world.owner[np.maximum(hit, 0)], EVERYWHERE)
    elsewhere = done & (owner != EVERYWHERE) & (owner != shard)
    target[elsewhere] = owner[elsewhere]
    return target


def route_shadow_exact(world: ShardWorld, remote: np.ndarray, shadow: ShadowRayBatch):
    """Unoccluded-so-far shadow rays: forward to the next unvisited box's shard."""
    return nearest_unvisited(world, remote, shadow.origin, shadow.direction, shadow.tmax,
                             shadow.visited)
