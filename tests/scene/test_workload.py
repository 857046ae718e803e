"""The ray-work estimate that places meshes: screen coverage from the camera, the pilot's
camera rays against the instances' boxes (against a brute-force oracle, with occlusion),
and the partition giving extra pieces to the mesh that covers more of the view, not the
one with more instances."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.model import Camera, Instance, Mesh, Scene
from nprt.scene.partition import partition
from nprt.scene.workload import (
    ASPECT,
    BASE_SHARE,
    HIT_WEIGHT,
    OPACITY,
    instance_work,
    pilot_work,
    screen_coverage,
)
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
    # The pilot: every ray crosses the big box first; none reaches the one behind. Each
    # instance also gets its share of BASE_SHARE views.
    base = BASE_SHARE / 2
    assert np.allclose(instance_work(scene), [base, base + 1 + HIT_WEIGHT * OPACITY])


def test_extra_pieces_go_to_the_mesh_that_covers_more_of_the_view():
    # Mesh 0: four cubes 3 in front of the camera (each 14-18 % of the view); mesh 1: eight
    # cubes 200 away (none). By instance count mesh 1 would be split; by ray work mesh 0 is.
    near = [Instance(0, translate(x, 0, 7)) for x in (-3, -1, 1, 3)]
    far = [Instance(1, translate(x, 0, -200)) for x in range(-8, 8, 2)]
    scene = Scene((_cube("near"), _cube("far")), tuple(near + far), camera=CAM)
    p = partition(scene, 3)
    assert p.summary()["split_meshes"] == [0]
    assert sorted(len(p.shard_instances(s)) for s in range(3)) == [2, 2, 8]


def _oracle_pilot(scene, nx: int, ny: int, opacity: float, hit_weight: float):
    """Every pilot ray against every box (no culling), in plain loops."""
    from nprt.scene.model import instance_world_bounds
    from nprt.scene.workload import _view

    eye, fwd, right, up, half_h = _view(scene)
    boxes = instance_world_bounds(scene)
    near = scene.camera.near_distance
    work = np.zeros(len(boxes))
    for py in range(ny):
        for px in range(nx):
            sx, sy = (px + 0.5) * 2 / nx - 1, (py + 0.5) * 2 / ny - 1
            d = fwd + sx * half_h * ASPECT * right + sy * half_h * up
            crossed = []
            for b, (lo, hi) in enumerate(boxes):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t0, t1 = (lo - eye) / d, (hi - eye) / d
                t_near = max(max(np.minimum(t0, t1)), near)
                if min(np.maximum(t0, t1)) >= t_near:
                    crossed.append((t_near, b))
            for r, (_, b) in enumerate(sorted(crossed)):
                work[b] += (1 - opacity) ** r * (1 + hit_weight * opacity)
    return work / (nx * ny) + BASE_SHARE / len(boxes)


def test_pilot_charges_each_box_the_rays_that_reach_it_as_a_brute_force_oracle():
    rng = np.random.default_rng(3)
    inst = [Instance(0, translate(*rng.uniform([-6, -4, -30], [6, 4, 5]))) for _ in range(12)]
    inst.append(Instance(1, translate(0, -6, -10)))  # a wide box low in the view
    scene = Scene((_cube("c"), _cube("slab", 8.0)), tuple(inst), camera=CAM)
    w = pilot_work(scene)
    from nprt.scene import workload

    n_rays = int(np.clip(workload.PILOT_PAIRS / screen_coverage(scene).sum(),
                         workload.MIN_PILOT_RAYS, workload.PILOT_RAYS))
    ny = round(np.sqrt(n_rays / ASPECT))
    nx = round(n_rays / ny)
    want = _oracle_pilot(scene, nx, ny, OPACITY, HIT_WEIGHT)
    assert np.allclose(w, want, rtol=1e-12, atol=1e-15)


def test_a_box_hidden_behind_another_gets_less_work_than_the_same_box_alone():
    front = Instance(0, translate(0, 0, 0))
    behind = Instance(0, translate(0, 0, -10))
    alone = pilot_work(Scene((_cube("c"),), (Instance(0, translate(0, 0, -10)),), camera=CAM))
    both = pilot_work(Scene((_cube("c"),), (front, behind), camera=CAM))
    # The hidden box sees the rays the front one lets through: (1 - OPACITY) of them.
    seen_alone, seen_behind = alone[0] - BASE_SHARE, both[1] - BASE_SHARE / 2
    assert seen_behind == pytest.approx((1 - OPACITY) * seen_alone, rel=0.05)
    assert both[0] > both[1]


def test_pilot_is_deterministic_and_rejects_a_bad_opacity():
    near = tuple(Instance(0, translate(x, 0, 7)) for x in (-3, -1, 1, 3))
    scene = Scene((_cube("near"),), near, camera=CAM)
    assert np.array_equal(pilot_work(scene), pilot_work(scene))
    with pytest.raises(ValueError, match="opacity must be in"):
        pilot_work(scene, opacity=0.0)
