"""Direct illumination of a diffuse plane against closed-form irradiance: a camera looks
straight down on y = 0, so every pixel sees a known plane point and L = rho / pi * E."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.model import DirectionalLight, PointLight, QuadLight
from tests.workers.helpers import (
    Material,
    assert_image_close,
    down_camera,
    fail_with_images,
    plane_mesh,
    plane_points_seen,
    render_image,
    single,
)

RHO = np.array([0.9, 0.6, 0.3])
HEIGHT, FOV_DEG = 3.0, 40.0  # camera above the origin, looking down -y
W = H = 16


def _camera():
    return down_camera(HEIGHT, FOV_DEG)


def _plane_scene(**lights):
    return single(plane_mesh(half=20.0, divisions=4), materials=(Material(albedo=tuple(RHO)),),
                  camera=_camera(), **lights)


def _radiance(irradiance_fn) -> np.ndarray:
    """(H, W, 3) pixel radiance rho / pi * E, box-filtered over each pixel's footprint."""
    pts = plane_points_seen(W, H, HEIGHT, FOV_DEG)
    e = irradiance_fn(pts.reshape(-1, 3)).reshape(H, W, -1)  # (H, W, sub^2) scalar E
    return RHO / np.pi * e.mean(axis=-1)[..., None]


def _assert_mean_close(img, ref, rtol, tmp_path, name):
    """The image mean is a much tighter estimate than any pixel: it catches small biases."""
    ratio = img.mean(axis=(0, 1)) / ref.mean(axis=(0, 1))
    if np.abs(ratio - 1).max() > rtol:
        fail_with_images(tmp_path, name, img, ref, np.abs(img - ref) / ref / (10 * rtol),
                         f"{name}: image mean / analytic = {ratio} (tolerance {rtol}): biased")


def test_point_light_on_plane_matches_inverse_square_cosine(tmp_path):
    pos, intensity = np.array([0.4, 1.2, -0.3]), 5.0

    def irradiance(x):
        v = pos - x
        r2 = (v * v).sum(axis=1)
        return intensity * v[:, 1] / np.sqrt(r2) / r2  # I cos(theta) / r^2, normal +y

    scene = _plane_scene(point_lights=(PointLight(tuple(pos), (intensity,) * 3),))
    # A point light is sampled deterministically; the only noise is the pixel jitter
    # against the box-filtered reference (8x8 quadrature): about 0.3% per pixel at 256 spp
    # (measured), so 2% per pixel is > 6 sigma and the image mean is held to 0.2%.
    img = render_image(scene, width=W, height=H, spp=256, bounces=1, shadow_rays=2)
    ref = _radiance(irradiance)
    _assert_mean_close(img, ref, 2e-3, tmp_path, "point_plane")
    assert_image_close(img, ref, tmp_path, "point_plane", rtol=0.02)


def test_directional_light_on_plane_matches_lambert_cosine(tmp_path):
    d = np.array([1.0, -2.0, 0.5])  # direction light travels
    e0 = 3.0
    cos = -d[1] / np.linalg.norm(d)
    scene = _plane_scene(directional_lights=(DirectionalLight(tuple(d), (e0,) * 3),))
    img = render_image(scene, width=W, height=H, spp=2, bounces=1)
    ref = np.broadcast_to(RHO / np.pi * e0 * cos, img.shape)
    assert_image_close(img, ref, tmp_path, "directional_plane", rtol=1e-5)


QUAD = dict(corner=(-0.6, 1.0, -0.4), edge_u=(1.0, 0.0, 0.0), edge_v=(0.0, 0.0, 0.8))
QUAD_L = 4.0  # edge_u x edge_v = (0, -0.8, 0): emits downward, camera sees its back


def polygon_irradiance(x: np.ndarray, verts: np.ndarray, radiance: float) -> np.ndarray:
    """Irradiance at points x (n, 3) with normal +y from a Lambertian polygon (Lambert's
    formula): E = L/2 |sum_i angle(a_i, b_i) n . unit(a_i x b_i)|, a_i = v_i - x,
    b_i = v_{i+1} - x. Assumes the whole polygon is above the points' tangent plane."""
    n = np.array([0.0, 1.0, 0.0])
    total = np.zeros(len(x))
    for i in range(len(verts)):
        a = verts[i] - x
        b = verts[(i + 1) % len(verts)] - x
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        c = np.cross(a, b)
        angle = np.arctan2(np.linalg.norm(c, axis=1), (a * b).sum(axis=1))
        total += angle * (c @ n) / np.linalg.norm(c, axis=1)
    return radiance / 2.0 * np.abs(total)


def test_polygon_irradiance_formula_matches_unit_disc_limit():
    # Guard on the reference itself: a tiny square of area A at height h straight above
    # gives E ~= L A / h^2; a huge one gives E -> pi L.
    tiny = np.array([[-1e-3, 1, -1e-3], [1e-3, 1, -1e-3], [1e-3, 1, 1e-3], [-1e-3, 1, 1e-3]])
    e = polygon_irradiance(np.zeros((1, 3)), tiny, 1.0)[0]
    assert e == pytest.approx(4e-6, rel=1e-5)
    huge = tiny * np.array([1e6, 1, 1e6])
    assert polygon_irradiance(np.zeros((1, 3)), huge, 1.0)[0] == pytest.approx(np.pi, rel=1e-5)


def _quad_reference():
    c, u, v = (np.array(QUAD[k]) for k in ("corner", "edge_u", "edge_v"))
    verts = np.stack([c, c + u, c + u + v, c + v])
    return _radiance(lambda x: polygon_irradiance(x, verts, QUAD_L))


# Per-pixel tolerances are >= 4 sigma of the worst pixel, sigma measured over 8 seeds
# (S=4: 1.2% at 1024 spp; S=1: 2%; S=0: 7.4% at 8192 spp); the image mean (256 pixels) is
# a far tighter estimate and catches a few-per-cent bias such as a wrong MIS weight.
@pytest.mark.parametrize("shadow_rays,spp,rtol,mean_rtol", [
    (4, 1024, 0.05, 0.003),  # NEE + MIS, the default
    pytest.param(1, 1024, 0.08, 0.005, marks=pytest.mark.slow),
    # BSDF sampling alone: the light is found only by bounce rays, so much noisier.
    pytest.param(0, 8192, 0.30, 0.01, marks=pytest.mark.slow),
])
def test_quad_light_on_plane_matches_polygon_irradiance(tmp_path, shadow_rays, spp, rtol,
                                                        mean_rtol):
    # bounces=1: the first hit does next-event estimation AND spawns a bounce ray that can
    # hit the quad, so the image is right only if the MIS weights of the two sum to one.
    scene = _plane_scene(quad_lights=(QuadLight(**QUAD, radiance=(QUAD_L,) * 3),))
    img = render_image(scene, width=W, height=H, spp=spp, bounces=1, shadow_rays=shadow_rays,
                       seed=11)
    ref = _quad_reference()
    _assert_mean_close(img, ref, mean_rtol, tmp_path, f"quad_plane_s{shadow_rays}")
    assert_image_close(img, ref, tmp_path, f"quad_plane_s{shadow_rays}", rtol=rtol)


QUAD2 = dict(corner=(0.3, 0.7, 0.2), edge_u=(0.4, -0.1, 0.0), edge_v=(0.0, 0.0, 0.5))
QUAD2_L = 6.0  # edge_u x edge_v = (-0.05, -0.2, 0): tilted, emitting down and to -x
POINT2 = (np.array([-0.8, 1.5, 0.6]), 3.0)


def test_several_lights_sum_on_plane(tmp_path):
    # Three lights: NEE picks one uniformly per shadow ray (pdf 1/3), and a bounce ray that
    # hits a quad is MIS-weighted with that same 1/3 pick, so both the pick and its use in
    # the weights show up in the mean. Worst-pixel sigma is 1.8% at 2048 spp (measured
    # over 8 seeds), so 8% per pixel is > 4 sigma; the mean is held to 0.3%.
    def verts(q):
        c, u, v = (np.array(q[k]) for k in ("corner", "edge_u", "edge_v"))
        return np.stack([c, c + u, c + u + v, c + v])

    pos, intensity = POINT2

    def irradiance(x):
        v = pos - x
        r2 = (v * v).sum(axis=1)
        return (polygon_irradiance(x, verts(QUAD), QUAD_L)
                + polygon_irradiance(x, verts(QUAD2), QUAD2_L)
                + intensity * v[:, 1] / np.sqrt(r2) / r2)

    scene = _plane_scene(quad_lights=(QuadLight(**QUAD, radiance=(QUAD_L,) * 3),
                                      QuadLight(**QUAD2, radiance=(QUAD2_L,) * 3)),
                         point_lights=(PointLight(tuple(pos), (intensity,) * 3),))
    img = render_image(scene, width=W, height=H, spp=2048, bounces=1, shadow_rays=4, seed=5)
    ref = _radiance(irradiance)
    _assert_mean_close(img, ref, 0.003, tmp_path, "three_lights")
    assert_image_close(img, ref, tmp_path, "three_lights", rtol=0.08)
