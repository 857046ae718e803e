"""Spawned-ray origins (nprt.workers.kernels.offset): rays leaving a flat or convex surface never
hit it
again, at any grazing angle, scale or distance from the origin, and the push off the
surface is a small fraction of the object, not a fixed epsilon."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nprt.scene.model import Instance, Scene
from nprt.scene.transform import similarity
from nprt.workers.kernels.sampling import normalize
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.surface import SurfaceTables
from tests.workers.helpers import mesh_from_trimesh, plane_mesh, trs
from tests.workers.oracles import frame, offset_rows

N_RAYS = 6000
SHAPES = {
    # Coplanar triangles: a ray leaving one may only hit a neighbour through rounding.
    "plane": lambda: plane_mesh(half=1.0, divisions=24),
    # Convex: a ray leaving a face outward cannot hit any face.
    "sphere": lambda: mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3)),
    # Convex, its vertices far from its own local origin (float32 spacing 1/1024 there).
    "offcentre": lambda: mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=2)
                                           .apply_translation([3000.0, -500.0, 250.0])),
}


def _setup(shape: str, scale: float, translation: float, seed: int):
    mesh = SHAPES[shape]()
    rng = np.random.default_rng(seed)
    axis = normalize(rng.normal(size=(1, 3)))[0]
    place = similarity(scale, translation * axis) @ trs((0, 0, 0), 1.0, tuple(axis), 37.0)
    scene = Scene((mesh,), (Instance(0, place),))
    table = InstanceTable(scene)
    geo = LocalGeometry({0: MeshGeometry(mesh)}, table, np.array([0], np.int32))
    return scene, table, geo, rng, place


def _hits(scene, table, geo, rng, place):
    """Rays from a sphere around the object at points of its local box; returns the
    surfaces of the rays that hit and the object's world size."""
    lo, hi = scene.meshes[0].bounds
    local = lo + rng.random((N_RAYS, 3)) * (hi - lo)
    target = local @ place[:3, :3].T + place[:3, 3]
    centre = place[:3, :3] @ (0.5 * (lo + hi)) + place[:3, 3]
    size = float(np.linalg.norm(place[:3, :3] @ (hi - lo)))
    origin = centre + 3.0 * size * normalize(rng.normal(size=(N_RAYS, 3)))
    direction = normalize(target - origin).astype(np.float32)
    t, inst, prim, u, v = geo.intersect_closest(origin, direction,
                                                np.full(N_RAYS, np.inf, np.float32))
    hit = inst >= 0
    tables = SurfaceTables(dict(enumerate(scene.meshes)), scene.materials, table)
    sf = tables.at(inst[hit], prim[hit], u[hit], v[hit], direction[hit])
    return sf, size


@pytest.mark.parametrize("translation", [0.0, 1e7], ids=["origin", "1e7"])
@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6], ids=["1e-6", "1", "1e6"])
@pytest.mark.parametrize("shape", list(SHAPES))
def test_rays_leaving_a_flat_or_convex_surface_never_hit_it_again(shape, scale, translation):
    scene, table, geo, rng, place = _setup(shape, scale, translation, seed=11)
    sf, _ = _hits(scene, table, geo, rng, place)
    n = len(sf.p)
    assert n > N_RAYS // 4, f"only {n} of {N_RAYS} rays hit the {shape}"
    # Outgoing directions from straight up to 1e-4 above the surface (cos to the normal).
    cos = 10.0 ** rng.uniform(-4, 0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s, t = frame(sf.ng)
    sin = np.sqrt(1 - cos**2)
    d = (cos[:, None] * sf.ng + (sin * np.cos(phi))[:, None] * s
         + (sin * np.sin(phi))[:, None] * t)
    d32 = d.astype(np.float32)
    keep = (d32.astype(np.float64) * sf.ng).sum(axis=1) > 0  # still above after rounding
    origin = offset_rows(sf.p, sf.p_err, sf.ng)
    inf = np.full(n, np.inf, np.float32)
    _, inst, _, _, _ = geo.intersect_closest(origin[keep], d32[keep], inf[keep])
    occluded = geo.intersect_occluded(origin[keep], d32[keep], inf[keep])
    assert (inst < 0).all() and not occluded.any(), (
        f"{int((inst >= 0).sum())} closest-hit and {int(occluded.sum())} shadow queries of "
        f"{int(keep.sum())} rays hit the {shape} they left")
    push = np.linalg.norm(origin - sf.p, axis=1)
    # Relative to the mesh's float32 local coordinates (in world units) and to float64
    # world coordinates, which are themselves good to 1.1e-16 |p|: never a fixed length.
    coords = scale * float(np.abs(scene.meshes[0].vertices).max())
    limit = 1e-5 * coords + 1e-14 * np.abs(sf.p).max(axis=1)
    assert (push > 0).all() and (push <= limit).all(), (
        f"push off the surface from {push.min():.3g} to {push.max():.3g}; local "
        f"coordinates up to {coords:.3g} in world units")
