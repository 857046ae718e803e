"""One global tie rule: where surfaces coincide (identical instances with different
materials, coplanar quads, a quad light flush on a wall) the same hit wins in the
reference and on any number of shards, so exact mode equals the reference bit for bit
even when the tied surfaces sit on different shards."""

from __future__ import annotations

import numpy as np
import pytest

from nprt.scene.model import Environment, Instance, Material, QuadLight, Scene
from nprt.scene.partition import partition
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
from tests.distributed.helpers import dump_images
from tests.workers.helpers import Camera, plane_mesh, trs

# One contribution per path (no next-event rays, one sample per pass), so every pixel's
# sum is a single float and the images can be compared bit for bit.
TIE_SETTINGS = dict(width=32, height=24, spp=2, spp_per_pass=1, bounces=3, shadow_rays=0,
                    seed=3)
WALL, WALL_TWIN, FLOOR, FLOOR_SHIFTED = range(4)


def tie_scene(with_wall: bool = True) -> Scene:
    """A wall and its twin (identical geometry and placement, different materials), two
    coplanar floors offset in their plane (their triangles tie where they overlap, and
    nearly tie elsewhere), and a quad light lying in the wall's plane. For K = 2, 3, 4 the
    partition puts at least one tied pair on two shards (both for K = 2 and 4).
    The twin comes first in the instance list, each floor's instance after the other's
    shard order, so the shard a ray meets first holds the instance that must lose."""
    meshes = tuple(plane_mesh(half=1.0, divisions=6, name=f"m{i}", material=i)
                   for i in range(4))
    materials = (Material("red", (0.8, 0.1, 0.1)), Material("green", (0.1, 0.8, 0.1)),
                 Material("blue", (0.1, 0.2, 0.8)), Material("sand", (0.7, 0.6, 0.3)))
    wall = trs((0.0, 2.0, -2.0), 2.0, (1, 0, 0), 90.0)  # the plane z = -2, y in [0, 4]
    floor = trs((0.0, 0.0, 0.0), 3.0)
    shifted = trs((0.37, 0.0, 0.21), 3.0)
    instances = [Instance(WALL_TWIN, wall)] + ([Instance(WALL, wall)] if with_wall else [])
    instances += [Instance(FLOOR_SHIFTED, shifted), Instance(FLOOR, floor)]
    light = QuadLight(corner=(-0.5, 1.5, -2.0), edge_u=(1.0, 0.0, 0.0), edge_v=(0.0, 1.0, 0.0),
                      radiance=(4.0, 4.0, 4.0))  # emits toward +z, out of the wall
    return Scene(meshes, tuple(instances), materials, quad_lights=(light,),
                 environment=Environment(radiance=(0.3, 0.3, 0.3)),
                 camera=Camera(eye=(0.4, 2.2, 5.0), target=(0.0, 1.0, -1.0), fov_deg=55.0),
                 name="ties")


@pytest.fixture(scope="module")
def tie_reference():
    return render(tie_scene(), RenderSettings(**TIE_SETTINGS)).film.image()


def test_reference_tie_goes_to_the_lower_instance():
    # The twin (instance 0) wins every tie with the wall: without the wall the image is
    # the same bit for bit; were the wall to win anywhere, its red would show.
    both = render(tie_scene(), RenderSettings(**TIE_SETTINGS)).film.image()
    twin_only = render(tie_scene(with_wall=False), RenderSettings(**TIE_SETTINGS)).film.image()
    assert np.array_equal(both, twin_only)


@pytest.mark.parametrize("k", [2, 3, 4], ids=lambda k: f"k{k}")
def test_exact_equals_reference_bit_for_bit_where_surfaces_coincide(ray_local, tie_reference,
                                                                    tmp_path, k):
    scene = tie_scene()
    owner = partition(scene, k).instance_shard
    inst_of = {i.mesh: n for n, i in enumerate(scene.instances)}
    # The partition balances ray work: at K = 3 (four meshes on three shards) it keeps the
    # lighter pair, the walls, together. A tie must cross shards for the test to bite.
    split = [owner[inst_of[a]] != owner[inst_of[b]]
             for a, b in ((WALL, WALL_TWIN), (FLOOR, FLOOR_SHIFTED))]
    assert any(split), f"k={k}: every tied pair shares a shard ({owner.tolist()})"
    img = render(scene, RenderSettings(**TIE_SETTINGS, shards=k)).film.image()
    if not np.array_equal(img, tie_reference):
        where = dump_images(tmp_path, f"ties_k{k}", img, tie_reference)
        bad = int((img != tie_reference).any(axis=-1).sum())
        raise AssertionError(f"k={k}: {bad} of {img.shape[0] * img.shape[1]} pixels differ "
                             f"from the reference; images in {where}")
