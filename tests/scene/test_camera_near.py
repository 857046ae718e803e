"""The camera's near distance: a scale-relative default, the scene file's `near`, and the
znear of a glTF file's camera."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from nprt.scene.errors import SceneError
from nprt.scene.gltf import load_gltf
from nprt.scene.io import load_scene, save_scene
from nprt.scene.model import NEAR_REL, Camera
from nprt.scene.transform import similarity, transform_scene
from tests.scene._util import rich_scene


def test_default_near_is_relative_to_the_view_distance_and_moves_with_the_scene():
    cam = Camera(eye=(0.0, 0.0, 8.0), target=(0.0, 0.0, 0.0))
    assert cam.near is None and cam.near_distance == pytest.approx(8.0 * NEAR_REL)
    scene = dataclasses.replace(rich_scene(), camera=cam)
    for s in (1e-6, 1e6):
        moved = transform_scene(scene, similarity(scale=s, translate=(1e7, -3e6, 2e5)))
        assert moved.camera.near_distance == pytest.approx(s * cam.near_distance, rel=1e-6)
    set_near = dataclasses.replace(scene, camera=dataclasses.replace(cam, near=0.5))
    near = transform_scene(set_near, similarity(scale=4.0)).camera.near
    assert near == pytest.approx(2.0, rel=1e-12)


@pytest.mark.parametrize("near", [None, 0.0, 0.125])
def test_camera_near_round_trips_through_a_scene_file(tmp_path, near):
    scene = dataclasses.replace(rich_scene(), camera=Camera((1, 2, 3), (0, 0.5, 0), near=near))
    back = load_scene(save_scene(scene, tmp_path / "s.json"))
    assert back.camera == scene.camera


def test_negative_near_in_a_scene_file_is_refused(tmp_path):
    scene = rich_scene()
    path = save_scene(scene, tmp_path / "s.json")
    path.write_text(path.read_text().replace('"fov_deg": 33.3', '"fov_deg": 33.3, "near": -1'))
    with pytest.raises(SceneError, match=r"camera\.near"):
        load_scene(path)


def _box_glb(path, camera: trimesh.scene.Camera | None, camera_xf=None):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), geom_name="box", node_name="n0")
    if camera is not None:
        scene.camera = camera
        scene.camera_transform = np.eye(4) if camera_xf is None else camera_xf
    path.write_bytes(scene.export(file_type="glb"))
    return path


def test_gltf_camera_znear_becomes_the_near_distance(tmp_path):
    cam = trimesh.scene.Camera(name="cam", fov=(60.0, 45.0), z_near=0.25, resolution=(64, 48))
    loaded = load_gltf(_box_glb(tmp_path / "cam.glb", cam))
    assert loaded.camera.near == pytest.approx(0.25)
    # Without a camera in the file the default (relative) near applies.
    assert load_gltf(_box_glb(tmp_path / "none.glb", None)).camera.near is None
