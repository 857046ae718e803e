"""The ray-work estimate that splits meshes into pieces: screen coverage from the camera,
and the partition giving extra pieces to the mesh that covers more of the view, not the
one with more instances."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.model import Camera, Instance, Mesh, Scene
from nprt.scene.partition import partition
from nprt.scene.workload import ASPECT, instance_work, screen_coverage
from tests.scene._util import translate


def _cube(name: str, half: float = 1.0) -> Mesh:
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)],
                 np.float32)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)
    return Mesh(name, v, f)


CAM = Camera(eye=(0.0, 0.0, 10.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=90.0)


def test_coverage_is_the_projected_box_over_the_view():
    # A 2x2x2 cube at the origin, seen from 10 away with a 90 degree view: its nearest face
    # (z = 1, 9 away) spans +-1/9 of the view's half height, its farthest +-1/11.
    scene = Scene((_cube("c"),), (Instance(0, translate(0, 0, 0)),), camera=CAM)
    want = (2 / 9) * (2 / (9 * ASPECT)) / 4
    assert screen_coverage(scene)[0] == pytest.approx(want, rel=1e-9)


def test_boxes_behind_the_camera_cover_nothing_and_around_it_everything():
    scene = Scene((_cube("c"), _cube("big", 50.0)),
                  (Instance(0, translate(0, 0, 30)), Instance(1, translate(0, 0, 0))),
                  camera=CAM)
    cover = screen_coverage(scene)
    assert cover[0] == 0.0 and cover[1] == 1.0
    assert np.allclose(instance_work(scene), cover + 0.5)


def test_extra_pieces_go_to_the_mesh_that_covers_more_of_the_view():
    # Mesh 0: four cubes 3 in front of the camera (each 14-18 % of the view); mesh 1: eight
    # cubes 200 away (none). By instance count mesh 1 would be split; by ray work mesh 0 is.
    near = [Instance(0, translate(x, 0, 7)) for x in (-3, -1, 1, 3)]
    far = [Instance(1, translate(x, 0, -200)) for x in range(-8, 8, 2)]
    scene = Scene((_cube("near"), _cube("far")), tuple(near + far), camera=CAM)
    p = partition(scene, 3)
    assert p.summary()["split_meshes"] == [0]
    assert sorted(len(p.shard_instances(s)) for s in range(3)) == [2, 2, 8]
