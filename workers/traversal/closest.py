"""The closest-hit stage of every shard's wavefront (the reference's too): this shard's
geometry plus the replicated quad lights, folded into the hit record a ray carries."""

from __future__ import annotations

import numpy as np

from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.wavefront.batch import LIGHT_BASE, RayBatch, precedes
from nprt.workers.wavefront.lights import LightSet


def resolve_closest(rays: RayBatch, geometry: LocalGeometry, lights: LightSet) -> RayBatch:
    """Fill the hit record (tmax, hit_inst, hit_prim, hit_u, hit_v) with the first, in
    the global order (`nprt.workers.wavefront.batch.precedes`), of the record the rays carry, this
    geometry's hits and the quad lights' (replicated everywhere, so every shard folds
    them in the same way)."""
    t, inst, prim, u, v = geometry.intersect_closest(rays.origin, rays.direction, rays.tmax,
                                                     rays.hit_inst, rays.hit_prim)
    got = inst >= 0
    hit_inst = np.where(got, inst, rays.hit_inst).astype(np.int32)
    hit_prim = np.where(got, prim, rays.hit_prim).astype(np.int32)
    tl, light = lights.intersect_quads(rays.origin, rays.direction, t)
    light_inst = (LIGHT_BASE - light).astype(np.int32)
    no_prim = np.full(len(rays), -1, np.int32)
    on_light = (light >= 0) & precedes(tl, light_inst, no_prim, t, hit_inst, hit_prim)
    return rays.replace(
        tmax=np.where(on_light, tl, t).astype(np.float32),
        hit_inst=np.where(on_light, light_inst, hit_inst).astype(np.int32),
        hit_prim=np.where(on_light, no_prim, hit_prim).astype(np.int32),
        hit_u=np.where(got & ~on_light, u, np.where(on_light, 0.0, rays.hit_u)).astype(np.float32),
        hit_v=np.where(got & ~on_light, v, np.where(on_light, 0.0, rays.hit_v)).astype(np.float32))
