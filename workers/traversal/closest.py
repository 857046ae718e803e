"""The closest-hit stage of every shard's wavefront (the reference's too): this shard's
geometry plus the replicated quad lights, folded into the hit record a ray carries."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import records
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.wavefront.batch import RayBatch
from nprt.workers.wavefront.lights import LightSet


def resolve_closest(rays: RayBatch, geometry: LocalGeometry, lights: LightSet) -> RayBatch:
    """Fill the hit record (tmax, hit_inst, hit_prim, hit_u, hit_v) with the first, in
    the global order (`nprt.workers.wavefront.batch.precedes`), of the record the rays carry, this
    geometry's hits and the quad lights' (replicated everywhere, so every shard folds
    them in the same way)."""
    t, inst, prim, u, v = geometry.intersect_closest(rays.origin, rays.direction, rays.tmax,
                                                     rays.hit_inst, rays.hit_prim)
    tl, light = lights.intersect_quads(rays.origin, rays.direction, t)
    tmax, hit_inst, hit_prim, hit_u, hit_v = records.with_lights(
        t, inst, prim, u, v, rays.hit_inst, rays.hit_prim, rays.hit_u, rays.hit_v, tl,
        np.ascontiguousarray(light, np.int32))
    return rays.replace(tmax=tmax, hit_inst=hit_inst, hit_prim=hit_prim, hit_u=hit_u,
                        hit_v=hit_v)
