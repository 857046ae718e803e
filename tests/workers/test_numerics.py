"""Numerical robustness: the slab test with zero direction components, self-intersection
of spawned rays, instances far from the origin, and Embree's side effects."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nprt.scene.model import DirectionalLight, PointLight
from nprt.workers.render import render
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.toplevel import InstanceTable
from nprt.workers.wavefront.reference import ReferenceRenderer
from tests.workers.helpers import (
    Camera,
    Environment,
    Instance,
    Material,
    RenderSettings,
    Scene,
    assert_image_close,
    down_camera,
    fail_with_images,
    mesh_from_trimesh,
    plane_mesh,
    plane_points_seen,
    render_image,
    single,
    trs,
)


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

    def intersect_closest(self, origin, direction, tmax, hit_inst=None, hit_prim=None):
        out = self.inner.intersect_closest(origin, direction, tmax, hit_inst, hit_prim)
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


def _slab_reference(o, d, tmax, boxes):
    """Independent float64 slab test without infinities: an axis with d == 0 keeps the ray
    iff lo < o < hi (origins exactly on a slab plane are excluded by the caller).
    returns set of (ray, box) pairs."""
    pairs = set()
    for r in range(len(o)):
        for k, (lo, hi) in enumerate(boxes):
            t_lo, t_hi, ok = -np.inf, np.inf, True
            for a in range(3):
                if d[r, a] == 0:
                    ok &= bool(lo[a] < o[r, a] < hi[a])
                else:
                    t0, t1 = (lo[a] - o[r, a]) / d[r, a], (hi[a] - o[r, a]) / d[r, a]
                    t_lo, t_hi = max(t_lo, min(t0, t1)), min(t_hi, max(t0, t1))
            if ok and t_hi >= max(t_lo, 0.0) and t_lo < tmax[r]:
                pairs.add((r, k))
    return pairs


def _slab_scene():
    cube = mesh_from_trimesh(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), "cube")
    flat = plane_mesh(half=3.0)  # zero thickness in y: only the padding gives it a slab
    return Scene((cube, flat), (Instance(0, trs((0.0, 1.0, 0.0))), Instance(1, np.eye(4)),
                                Instance(0, trs((2.0, 0.0, -2.0), 0.5, (1, 1, 0), 30.0))))


def test_slab_test_with_zero_direction_components_gives_no_nan_and_the_right_boxes():
    table = InstanceTable(_slab_scene())
    rng = np.random.default_rng(3)
    n = 4000
    o = rng.uniform(-4, 4, size=(n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3))
    zero = rng.random((n, 3)) < 0.4  # many rays with one or two zero components
    zero[np.arange(0, n, 7)] = [True, True, False]  # and some along a single axis
    d = np.where(zero, 0.0, d)
    d[np.all(d == 0, axis=1)] = [0.0, 0.0, 1.0]
    d = np.where(rng.random((n, 3)) < 0.5, d, -d)  # includes -0.0 components
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(0.5, 6.0, n), np.inf).astype(np.float32)
    ray, inst, t_enter, t_exit = table.box_entries(o, d, tmax, np.arange(len(table)))
    assert not np.isnan(t_enter).any() and not np.isnan(t_exit).any()
    got = set(zip(ray.tolist(), inst.tolist(), strict=True))
    boxes = [(b[0], b[1]) for b in table.world_bounds]
    want = _slab_reference(o.astype(np.float64), d.astype(np.float64), tmax, boxes)
    assert got == want, f"missing {sorted(want - got)[:5]}, extra {sorted(got - want)[:5]}"


def test_axis_parallel_rays_hit_a_flat_box_and_origins_on_slab_planes_make_no_nan():
    table = InstanceTable(_slab_scene())
    lo, hi = table.world_bounds[1]  # the flat plane: y extent is only the padding
    o = np.array([[0.5, 5.0, 0.5],  # straight down onto the plane (d.x = d.z = 0)
                  [0.5, 0.0, -9.0],  # inside the plane's thin slab, along +z
                  [0.5, 0.1, -9.0],  # just above the slab, along +z: misses it
                  [lo[0], 2.0, 0.0],  # origin on the x = lo plane, d.x = 0
                  [hi[0], 2.0, 0.0]], np.float32)
    d = np.array([[0, -1, 0], [0, 0, 1], [0, 0, 1], [-0.0, -1, 0], [0, -1, -0.0]], np.float32)
    tmax = np.full(len(o), np.inf, np.float32)
    ray, inst, t_enter, t_exit = table.box_entries(o, d, tmax, np.array([1]))
    assert np.isfinite(t_enter[ray < 3]).all() and not np.isnan(t_exit).any()
    hits = set(ray.tolist())
    assert {0, 1} <= hits and 2 not in hits, f"rays meeting the plane's box: {sorted(hits)}"
    # Rays 3 and 4 lie in a face plane of the padded box: either answer is safe, since the
    # padding keeps geometry strictly inside, but there must be no NaN (checked above).
    t0 = t_enter[ray == 0][0]
    assert 5.0 - 1e-3 < t0 <= 5.0, f"entry distance {t0} for a ray 5 above the plane"


def test_axis_aligned_shadow_rays_find_their_occluder(tmp_path):
    # Light travelling along (1, -1, 0): every shadow ray has an exact zero z component.
    # A cube [-0.5, 0.5] x [0.5, 1.5] x [-0.5, 0.5] over the plane y = 0 casts the shadow
    # x in [0, 2], |z| <= 0.5; a camera 6 above the origin sees the cube's top face as
    # plane points |x|, |z| <= 0.5 * 6 / 4.5. Pixels whose whole footprint falls in one
    # region must equal that region's direct radiance exactly.
    e, rho_plane, rho_cube, cam_h, fov, w = 2.0, 0.6, 0.3, 6.0, 60.0, 48
    cube = mesh_from_trimesh(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), "cube", material=1)
    scene = Scene((plane_mesh(half=20.0), cube),
                  (Instance(0, np.eye(4)), Instance(1, trs((0.0, 1.0, 0.0)))),
                  materials=(Material(albedo=(rho_plane,) * 3), Material(albedo=(rho_cube,) * 3)),
                  directional_lights=(DirectionalLight((1.0, -1.0, 0.0), (e,) * 3),),
                  camera=down_camera(cam_h, fov))
    img = render_image(scene, width=w, height=w, spp=4, bounces=1)
    pts = plane_points_seen(w, w, cam_h, fov)  # (h, w, 64, 3)
    x, z = pts[..., 0], pts[..., 2]
    top = 0.5 * cam_h / 4.5
    on_cube = (np.abs(x) <= top) & (np.abs(z) <= top)
    shadow = ~on_cube & (x >= 0) & (x <= 2) & (np.abs(z) <= 0.5)
    cos = np.sqrt(0.5)
    value = np.where(on_cube, rho_cube, np.where(shadow, 0.0, rho_plane)) / np.pi * e * cos
    pure = (value == value[..., :1]).all(axis=-1)  # (h, w) whole footprint in one region
    assert shadow.all(axis=-1).sum() >= 20, "too few pixels entirely in the shadow"
    ref = np.repeat(value[..., 0][..., None], 3, axis=-1)
    assert_image_close(img, ref, tmp_path, "axis_shadow", rtol=1e-5, atol=1e-6, mask=pure)


def _camera_on_wall(with_wall: bool, near: float | None) -> Scene:
    """A camera whose eye lies exactly on a wall (the plane z = 0, exact in float32 and
    float64), looking straight out of it at a sphere lit by a directional light that
    travels toward the wall. Black environment: the wall can change the image only
    where camera rays hit it."""
    wall = plane_mesh(half=4.0, divisions=6, name="wall")
    ball = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3), "ball")
    upright = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
    instances = (Instance(1, trs((0.0, 1.0, 4.0))),) + ((Instance(0, upright),) if with_wall
                                                         else ())
    return Scene((wall, ball), instances, materials=(Material(albedo=(0.6, 0.6, 0.6)),),
                 directional_lights=(DirectionalLight((0.2, -0.5, -1.0), (2.0, 2.0, 2.0)),),
                 camera=Camera(eye=(0.3, 1.1, 0.0), target=(0.3, 1.1, 5.0), fov_deg=60.0,
                               near=near))


def test_camera_exactly_on_a_surface_sees_the_scene(tmp_path):
    kw = dict(width=32, height=32, spp=2, bounces=1, seed=4)
    seen = render_image(_camera_on_wall(True, None), **kw)
    ref = render_image(_camera_on_wall(False, None), **kw)
    assert ref.max() > 0 and (ref.max(axis=-1) == 0).mean() > 0.2, "sphere on black expected"
    assert_image_close(seen, ref, tmp_path, "camera_on_wall", rtol=1e-6, atol=1e-7)
    # Without a near distance the wall is seen at t = 0 in every direction, from its
    # unlit side: the sphere is gone.
    blocked = render_image(_camera_on_wall(True, 0.0), **kw)
    assert not blocked.any()
