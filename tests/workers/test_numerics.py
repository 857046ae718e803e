"""Numerical robustness: the slab test with zero direction components, self-intersection
of spawned rays, instances far from the origin, and Embree's side effects."""

from __future__ import annotations

import numpy as np
import trimesh

from tests.workers.helpers import mesh_from_trimesh
from workers.geometry import MeshGeometry


def test_mesh_geometry_leaves_caller_tmax_unchanged():
    # embreex writes tfar back into the `dists` array it is given; a caller's tmax (or a
    # shared constant buffer of inf) must not be overwritten by one query's hits.
    geo = MeshGeometry(mesh_from_trimesh(trimesh.creation.icosphere(radius=1.0)))
    o = np.zeros((3, 3), np.float32)
    d = np.eye(3, dtype=np.float32)
    tmax = np.full(3, np.inf, np.float32)
    t, prim, _, _ = geo.intersect_closest(o, d, tmax)
    assert (prim >= 0).all() and np.allclose(t, 1.0, atol=0.05)
    assert np.isinf(tmax).all(), f"intersect_closest overwrote the caller's tmax: {tmax}"
    geo.intersect_occluded(o, d, tmax)
    assert np.isinf(tmax).all(), f"intersect_occluded overwrote the caller's tmax: {tmax}"
