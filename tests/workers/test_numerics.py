"""Numerical robustness: the slab test with zero direction components, self-intersection
of spawned rays, instances far from the origin, and Embree's side effects."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from scene.model import DirectionalLight, PointLight
from tests.workers.helpers import (
    Camera,
    Environment,
    Material,
    RenderSettings,
    assert_image_close,
    fail_with_images,
    mesh_from_trimesh,
    plane_mesh,
    render_image,
    single,
    trs,
)
from workers.geometry import MeshGeometry
from workers.reference import ReferenceRenderer
from workers.render import render


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


class _RecordingGeometry:
    """Wraps a LocalGeometry, recording every occlusion query's answers (bench-free spy)."""

    def __init__(self, inner):
        self.inner, self.occluded = inner, []
        self.closest_hits = 0

    def intersect_closest(self, origin, direction, tmax):
        out = self.inner.intersect_closest(origin, direction, tmax)
        self.closest_hits += int((out[1] >= 0).sum())
        return out

    def intersect_occluded(self, origin, direction, tmax):
        occ = self.inner.intersect_occluded(origin, direction, tmax)
        self.occluded.append(occ)
        return occ


def _render_spied(scene, **kw):
    settings = RenderSettings(**kw)
    renderer = ReferenceRenderer(scene, settings)
    spy = renderer.geometry = _RecordingGeometry(renderer.geometry)
    img = render(scene, settings, renderer=renderer).film.image()
    return img, spy


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5], ids=["origin", "1e3", "1e5"])
@pytest.mark.parametrize("light", ["directional", "point"])
def test_grazing_light_on_tessellated_plane_has_no_self_shadowing(tmp_path, offset, light):
    # A flat, finely tessellated, rotated plane lit 2 degrees above its horizon: nothing
    # can block any shadow ray, so every occlusion is acne (a ray re-hitting the surface it
    # left, often a neighbouring triangle at the grazing angle). Bounce rays likewise must
    # never hit anything, or they would lose the environment term.
    rho, env, elev = 0.5, 0.25, np.radians(2.0)
    xf = trs((offset, -0.5 * offset, 0.25 * offset), 1.0, (1, 0.3, -0.2), 35.0)
    n = xf[:3, :3] @ [0.0, 1.0, 0.0]
    tangent = xf[:3, :3] @ [1.0, 0.0, 0.2]
    tangent /= np.linalg.norm(tangent)
    to_light = np.cos(elev) * tangent + np.sin(elev) * n  # unit, 2 degrees above horizon
    centre = xf[:3, 3]
    if light == "directional":
        lights = dict(directional_lights=(DirectionalLight(tuple(-to_light), (1.0,) * 3),))
        e = np.sin(elev) * np.ones((1, 1))  # E cos(theta), uniform over the plane
    else:
        pos = centre + 50.0 * to_light
        lights = dict(point_lights=(PointLight(tuple(pos), (2500.0,) * 3),))
        e = None  # varies across the plane; checked through the occlusion count only
    eye = centre + 3.0 * n + 0.5 * tangent
    scene = single(plane_mesh(half=4.0, divisions=24), xf, materials=(Material(albedo=(rho,) * 3),),
                   environment=Environment(radiance=(env,) * 3),
                   camera=Camera(eye=tuple(eye), target=tuple(centre), up=tuple(tangent),
                                 fov_deg=60.0), **lights)
    img, spy = _render_spied(scene, width=32, height=32, spp=4, bounces=1, shadow_rays=2)
    occ = np.concatenate(spy.occluded)
    assert len(occ) > 1000, "the light should have been sampled from every hit"
    self_hits = spy.closest_hits - 32 * 32 * 4  # every camera ray hits the plane
    if occ.any() or self_hits:
        fail_with_images(tmp_path, f"acne_{light}", img, img, np.zeros(img.shape[:2]),
                         f"{occ.sum()} of {len(occ)} shadow rays wrongly occluded; "
                         f"{self_hits} bounce rays hit the plane they left")
    if e is not None:
        ref = np.broadcast_to(rho / np.pi * e + rho * env, img.shape)
        assert_image_close(img, ref, tmp_path, "grazing_plane", rtol=1e-4)


def _lit_sphere(centre):
    """Unit convex sphere lit by a point light, camera 4 units away, everything relative to
    `centre`. Convex: no shadow or bounce ray can hit it again, however far its origin is
    pushed off the surface, so the image depends only on the camera hits and on float64
    shading, not on the float32 spawn offsets (which grow with distance from the origin)."""
    c = np.asarray(centre, np.float64)
    sphere = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=1.0))
    return single(sphere, trs(c), materials=(Material(albedo=(0.8, 0.8, 0.8)),),
                  point_lights=(PointLight(tuple(c + [2.0, 3.0, 4.0]), (30.0,) * 3),),
                  camera=Camera(eye=tuple(c + [0.0, 1.0, 4.0]), target=tuple(c), fov_deg=40.0))


@pytest.mark.parametrize("distance", [1e5, 1e6], ids=["1e5", "1e6"])
def test_far_away_instance_renders_like_at_origin(tmp_path, distance):
    # Camera and scene move together by a vector whose sum with the camera position is
    # exact in float32, so camera rays are identical in the instance's local space.
    kw = dict(width=32, height=32, spp=4, bounces=1, seed=2)
    ref = render_image(_lit_sphere((0.0, 0.0, 0.0)), **kw)
    img = render_image(_lit_sphere((distance, -distance, 0.5 * distance)), **kw)
    lit = ref.max(axis=-1) > 0
    assert lit.mean() > 0.2, "reference sphere should fill part of the frame"
    assert (img.max(axis=-1) > 0).sum() >= lit.sum() * 0.99, "far-away instance renders black"
    assert_image_close(img, ref, tmp_path, f"far_sphere_{distance:g}", rtol=1e-4, atol=1e-6)
