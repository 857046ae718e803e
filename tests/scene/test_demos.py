"""Procedural demos: size requirements per size knob, determinism, lights, camera, layout."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.demos import DEMOS, SIZES, make_demo
from nprt.scene.errors import SceneError
from nprt.scene.model import instance_world_bounds

MB = 1_000_000


@pytest.fixture(scope="module")
def default_scenes():
    # How long generation takes is a benchmark figure, not a test (machine load decides it).
    return {name: make_demo(name, "default") for name in DEMOS}


@pytest.mark.parametrize("name", list(DEMOS))
def test_default_demo_is_massive_but_fits_the_byte_budget(default_scenes, name):
    scene = default_scenes[name]
    s = scene.summary()
    assert s["base_meshes"] >= 3
    assert s["instances"] >= 20
    assert s["instanced_triangles"] >= 1_000_000
    assert s["mesh_bytes"] <= 50 * MB


@pytest.mark.parametrize("name", list(DEMOS))
def test_small_demo_is_much_lighter(name):
    s = make_demo(name, "small").summary()
    assert 40_000 <= s["instanced_triangles"] <= 250_000
    assert s["mesh_bytes"] <= 3 * MB
    assert s["instances"] >= 10


@pytest.mark.parametrize("name", list(DEMOS))
def test_tiny_demo_has_a_few_thousand_triangles(name):
    s = make_demo(name, "tiny").summary()
    assert 500 <= s["instanced_triangles"] <= 6_000
    assert s["base_meshes"] >= 3


@pytest.mark.parametrize("name", list(DEMOS))
def test_demo_is_deterministic_from_its_seed(name):
    a, b, c = (make_demo(name, "tiny", seed=s) for s in (5, 5, 6))
    for ma, mb in zip(a.meshes, b.meshes, strict=True):
        assert np.array_equal(ma.vertices, mb.vertices) and np.array_equal(ma.faces, mb.faces)
    xa = np.stack([i.transform for i in a.instances])
    assert np.array_equal(xa, np.stack([i.transform for i in b.instances]))
    xc = np.stack([i.transform for i in c.instances])
    assert xa.shape != xc.shape or not np.array_equal(xa, xc), "seed has no effect"


@pytest.mark.parametrize("name", list(DEMOS))
def test_demo_instances_sit_on_the_ground_and_overlap(name):
    scene = make_demo(name, "small")
    assert all(i.transform.dtype == np.float64 for i in scene.instances)
    boxes = instance_world_bounds(scene)  # (n, 2, 3)
    ground = scene.meshes[0]
    assert ground.name == "ground" and float(boxes[:, 0, 1].min()) >= -1e-6
    objects = boxes[1:]  # everything but the ground plane
    lo, hi = objects[:, 0], objects[:, 1]
    inter = np.all(np.minimum(hi[:, None], hi[None]) > np.maximum(lo[:, None], lo[None]), -1)
    np.fill_diagonal(inter, False)
    assert inter.any(), "no two instance boxes overlap"


@pytest.mark.parametrize("name", list(DEMOS))
def test_demo_is_lit_from_above_by_a_panel_and_a_sky(name):
    scene = make_demo(name, "tiny")
    boxes = instance_world_bounds(scene)
    assert scene.environment.kind == "sky"
    assert 0.1 <= max(scene.environment.zenith) <= 2.0
    assert len(scene.quad_lights) >= 1
    light = scene.quad_lights[0]
    normal = np.cross(light.edge_u, light.edge_v)
    assert normal[1] < 0, "panel must face down"
    assert light.corner[1] > boxes[:, 1, 1].max(), "panel must hang above every instance"
    assert len({m.albedo for m in scene.materials}) >= 3


@pytest.mark.parametrize("name", list(DEMOS))
def test_demo_camera_looks_at_the_scene_from_outside(name):
    scene = make_demo(name, "small")
    boxes = instance_world_bounds(scene)[1:]
    lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
    eye, target = np.array(scene.camera.eye), np.array(scene.camera.target)
    assert np.all(target >= lo) and np.all(target <= hi)
    assert eye[1] > 0 and np.linalg.norm(eye - target) > 0.25 * np.linalg.norm(hi - lo)


def test_forest_has_three_tree_shapes_of_many_leaf_quads(default_scenes):
    scene = default_scenes["forest"]
    trees = [m for m in scene.meshes if m.name != "ground"]
    assert len(trees) >= 3
    assert all(len(m.faces) >= 5_000 for m in trees)
    sizes = [np.ptp(m.vertices, axis=0) for m in trees]
    assert len({tuple(np.round(s, 1)) for s in sizes}) == len(trees), "tree shapes repeat"


def test_city_has_at_least_ten_building_meshes_with_windows(default_scenes):
    scene = default_scenes["city"]
    buildings = [m for m in scene.meshes if m.name != "ground"]
    assert len(buildings) >= 10
    # A plain box has 10 triangles on its walls and roof; windows add thousands.
    assert all(len(m.faces) > 1_000 for m in buildings)


def test_sculptures_are_high_poly_and_displaced(default_scenes):
    scene = default_scenes["sculpture"]
    shapes = [m for m in scene.meshes if m.name in ("blob", "torus", "column")]
    assert len(shapes) == 3
    for m in shapes:
        assert len(m.faces) >= 50_000 and m.normals is not None
    blob = next(m for m in shapes if m.name == "blob")
    radius = np.linalg.norm(blob.vertices, axis=1)
    assert radius.max() - radius.min() > 0.2  # far from a sphere


@pytest.mark.parametrize(("name", "size"), [("volcano", "tiny"), ("forest", "huge")])
def test_unknown_demo_or_size_is_refused(name, size):
    with pytest.raises(SceneError, match="unknown"):
        make_demo(name, size)


def test_sizes_are_listed():
    assert SIZES == ("default", "small", "tiny", "massive")
    # massive is forest's alone; asking another demo for it names the sizes it has
    with pytest.raises(SceneError, match="unknown size 'massive'.*default, small, tiny$"):
        make_demo("city", "massive")
