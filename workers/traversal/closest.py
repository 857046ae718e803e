"""The closest-hit stage of every shard's wavefront (the reference's too): this shard's
geometry plus the replicated quad lights, folded into the hit record a ray carries."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import records
from nprt.workers.traversal.local import LocalGeometry, NearestRemote
from nprt.workers.wavefront.batch import RayBatch
from nprt.workers.wavefront.lights import LightSet


def resolve_closest(rays: RayBatch, geometry: LocalGeometry, lights: LightSet) -> RayBatch:
    """Fill the hit record (tmax, hit_inst, hit_prim, hit_u, hit_v) with the first, in
    the global order (`nprt.workers.wavefront.batch.precedes`), of the record the rays carry, this
    geometry's hits and the quad lights' (replicated everywhere, so every shard folds
    them in the same way)."""
    t, inst, prim, u, v = geometry.intersect_closest(rays.origin, rays.direction, rays.tmax,
                                                     rays.hit_inst, rays.hit_prim)
    return _with_lights(rays, lights, t, inst, prim, u, v)


def resolve_closest_routed(rays: RayBatch, geometry: LocalGeometry, lights: LightSet,
                           cand_owner: np.ndarray) -> tuple[RayBatch, NearestRemote]:
    """`resolve_closest`, and from the same walk of the top level exact forwarding's next
    stop among the boxes of cand_owner (m,) int32 (`LocalGeometry.closest_routed`), for
    `nprt.workers.routing.exact.route_exact` to cut at the final tmax."""
    t, inst, prim, u, v, near = geometry.closest_routed(
        rays.origin, rays.direction, rays.tmax, rays.hit_inst, rays.hit_prim, cand_owner,
        rays.visited)
    return _with_lights(rays, lights, t, inst, prim, u, v), near


def _with_lights(rays, lights, t, inst, prim, u, v) -> RayBatch:
    tl, light = lights.intersect_quads(rays.origin, rays.direction, t)
    tmax, hit_inst, hit_prim, hit_u, hit_v = records.with_lights(
        t, inst, prim, u, v, rays.hit_inst, rays.hit_prim, rays.hit_u, rays.hit_v, tl,
        np.ascontiguousarray(light, np.int32))
    return rays.replace(tmax=tmax, hit_inst=hit_inst, hit_prim=hit_prim, hit_u=hit_u,
                        hit_v=hit_v)
