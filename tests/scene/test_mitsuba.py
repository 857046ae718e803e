"""nprt's reference renderer against Mitsuba 3 (scalar_rgb) on the same scenes, exported by
`nprt.scene.mitsuba`: 8x8 block means agree within noise (|z| <= 4), with each block's
standard error estimated from two seeds of each renderer. The demos are at their default
size (the image is small: 64x48, 32 spp)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from nprt.scene.demos import make_demo
from nprt.scene.model import (
    Camera,
    DirectionalLight,
    Environment,
    Instances,
    Material,
    Mesh,
    PointLight,
    QuadLight,
    Scene,
)
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.blocks import block_means, block_sigma

mitsuba_export = pytest.importorskip("nprt.scene.mitsuba")
pytest.importorskip("mitsuba")

WIDTH, HEIGHT, SPP, BOUNCES = 64, 48, 32, 5
SEEDS = (1, 2)
Z_MAX = 4.0
SIGMA_FLOOR_REL = 1e-4  # as nprt.workers.stats.blocks: float rounding is not a difference


def pooled_block_z(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]):
    """(h/8, w/8, 3) z-scores of the mean of a's two seeds against b's: each renderer's
    block variance is estimated from its own two seeds (their difference), so neither
    renderer's noise is taken for the other's."""
    ma = 0.5 * (block_means(a[0]) + block_means(a[1]))
    mb = 0.5 * (block_means(b[0]) + block_means(b[1]))
    var = 0.5 * (block_sigma(*a) ** 2 + block_sigma(*b) ** 2)  # of each mean of two
    sigma = np.sqrt(var + (SIGMA_FLOOR_REL * np.abs(mb)) ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sigma > 0, (ma - mb) / sigma, np.where(ma == mb, 0.0, np.inf))


def textured_scene() -> Scene:
    """A checker-textured floor and instanced boxes under a point light, a directional
    light, a quad light (above everything, facing down) and a constant environment: every
    feature the exporter maps exactly."""
    h = 4.0
    v = np.array([[-h, 0, h], [h, 0, h], [h, 0, -h], [-h, 0, -h]], np.float32)
    floor = Mesh("floor", v, np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
                 normals=np.tile(np.float32([0, 1, 0]), (4, 1)),
                 uvs=np.array([[0, 0], [2, 0], [2, 2], [0, 2]], np.float32), material=0)
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube = Mesh("cube", np.asarray(box.vertices + [0, 0.5, 0], np.float32),
                np.asarray(box.faces, np.uint32), material=1)
    checker = np.zeros((4, 4, 3), np.float32)
    checker[(np.add.outer(np.arange(4), np.arange(4)) % 2) == 0] = (0.9, 0.6, 0.2)
    checker[(np.add.outer(np.arange(4), np.arange(4)) % 2) == 1] = (0.1, 0.3, 0.7)
    xf = np.tile(np.eye(4), (4, 1, 1))
    for k, (x, z, yaw) in enumerate([(-1.5, -1.0, 0.3), (1.2, -0.5, 0.9), (0.0, 1.2, 0.0)]):
        c, s = np.cos(yaw), np.sin(yaw)
        xf[k + 1, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        xf[k + 1, :3, 3] = (x, 0.0, z)
    return Scene(
        meshes=(floor, cube), instances=Instances(np.array([0, 1, 1, 1]), xf),
        materials=(Material("checker", texture=checker), Material("grey", (0.7, 0.7, 0.7))),
        # Beside the floor: Mitsuba's rectangle casts a shadow of the directional light
        # (nprt's quads are transparent from behind), and this one's falls off the floor.
        quad_lights=(QuadLight((4.5, 5.0, -1.0), (2.0, 0, 0), (0, 0, 2.0), (9.0, 9.0, 8.0)),),
        point_lights=(PointLight((2.0, 3.0, 2.0), (8.0, 7.0, 6.0)),),
        directional_lights=(DirectionalLight((0.4, -1.0, 0.3), (1.5, 1.5, 1.7)),),
        environment=Environment("constant", radiance=(0.2, 0.25, 0.3)),
        camera=Camera(eye=(0.0, 4.0, 7.0), target=(0.0, 0.5, 0.0), fov_deg=45.0),
        name="textured")


def nprt_images(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    return tuple(render(scene, RenderSettings(width=WIDTH, height=HEIGHT, spp=SPP,
                                              bounces=BOUNCES, seed=s)).film.image()
                 for s in SEEDS)


def mitsuba_images(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    return tuple(mitsuba_export.render_mitsuba(scene, width=WIDTH, height=HEIGHT, spp=SPP,
                                               bounces=BOUNCES, seed=s) for s in SEEDS)


@pytest.mark.slow
@pytest.mark.parametrize("scene", [
    pytest.param(lambda: make_demo("sculpture", "default"), id="sculpture"),
    pytest.param(lambda: make_demo("city", "default"), id="city"),
    pytest.param(lambda: make_demo("forest", "default"), id="forest"),
    pytest.param(textured_scene, id="textured"),
])
def test_reference_matches_mitsuba_within_noise(scene, tmp_path):
    scene = scene()
    ours, theirs = nprt_images(scene), mitsuba_images(scene)
    z = pooled_block_z(theirs, ours)
    worst = np.unravel_index(np.argmax(np.abs(z)), z.shape)
    if np.abs(z).max() > Z_MAX:
        np.save(tmp_path / "nprt.npy", np.stack(ours))
        np.save(tmp_path / "mitsuba.npy", np.stack(theirs))
        np.save(tmp_path / "z.npy", z)
    assert np.abs(z).max() <= Z_MAX, (
        f"{scene.name}: block {worst[:2]} channel {worst[2]} differs by z = {z[worst]:.2f} "
        f"({int((np.abs(z) > Z_MAX).sum())} of {z.size} beyond {Z_MAX}); images in {tmp_path}")


def test_exported_quad_light_keeps_corner_edges_and_facing():
    """The rectangle spans nprt's corner + a u + b v and emits along cross(u, v)."""
    import mitsuba as mi

    q = QuadLight((1.0, 2.0, 3.0), (2.0, 0.0, 0.0), (0.0, 0.0, -1.0), (1.0, 1.0, 1.0))
    scene = dataclasses.replace(textured_scene(), quad_lights=(q,))
    d = mitsuba_export.to_mitsuba(scene, width=4, height=4, spp=1, bounces=1)
    rect = mi.load_dict({"type": "scene", "q": d["quad0"]}).shapes()[0]
    box = rect.bbox()
    np.testing.assert_allclose([list(box.min), list(box.max)], [[1, 2, 2], [3, 2, 3]],
                               atol=1e-6)
    si = rect.eval_parameterization(mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(list(si.n), np.cross(q.edge_u, q.edge_v) / 2.0, atol=1e-6)


def test_export_refuses_bad_sizes():
    with pytest.raises(ValueError, match="spp"):
        mitsuba_export.to_mitsuba(textured_scene(), width=8, height=8, spp=0, bounces=1)
