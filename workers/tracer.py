"""Whole-scene closest-hit and shadow queries in one process: local geometry plus the
replicated quad lights. Used by the reference renderer (all instances) and the raw
throughput benchmark."""

from __future__ import annotations

import numpy as np

from workers.batch import LIGHT_BASE, RayBatch, ShadowRayBatch
from workers.lights import LightSet
from workers.local import LocalGeometry


def resolve_closest(rays: RayBatch, geometry: LocalGeometry, lights: LightSet) -> RayBatch:
    """Fill the hit record (tmax, hit_inst, hit_prim, hit_u, hit_v) with the closest of
    this geometry and the quad lights, starting from the record the rays carry."""
    t, inst, prim, u, v = geometry.intersect_closest(rays.origin, rays.direction, rays.tmax)
    got = inst >= 0
    tl, light = lights.intersect_quads(rays.origin, rays.direction, np.minimum(t, rays.tmax))
    on_light = light >= 0
    hit_inst = np.where(got, inst, rays.hit_inst)
    hit_inst = np.where(on_light, LIGHT_BASE - light, hit_inst).astype(np.int32)
    return rays.replace(
        tmax=np.where(on_light, tl, t).astype(np.float32),
        hit_inst=hit_inst,
        hit_prim=np.where(got & ~on_light, prim, rays.hit_prim).astype(np.int32),
        hit_u=np.where(got, u, rays.hit_u).astype(np.float32),
        hit_v=np.where(got, v, rays.hit_v).astype(np.float32))


def unoccluded(shadow: ShadowRayBatch, geometry: LocalGeometry) -> np.ndarray:
    """(n,) bool: shadow rays that no geometry here blocks."""
    return ~geometry.intersect_occluded(shadow.origin, shadow.direction, shadow.tmax)
