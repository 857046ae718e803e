"""Instancing: a mesh rendered through instance transforms equals the same mesh baked into
world space, and renders are (nearly) invariant under moving scene and camera together."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nprt.scene.model import DirectionalLight, PointLight
from tests.workers.helpers import (
    Camera,
    Environment,
    Instance,
    Material,
    Mesh,
    Scene,
    fail_with_images,
    mesh_from_trimesh,
    render_image,
    trs,
)

SETTINGS = dict(width=48, height=48, spp=4, bounces=2, seed=1)
# Three placements of one torus: rotations about skew axes, non-uniform scale, translation.
PLACEMENTS = [trs((0, 0, 0), 1.0, (1, 0, 0), 60.0),
              trs((2.2, 0.3, -1.0), (0.5, 1.3, 0.8), (0, 1, 1), -30.0),
              trs((-2.0, -0.5, 0.5), 0.7, (1, 1, 1), 110.0)]


def _torus(snap: float | None = None) -> Mesh:
    tm = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=32,
                                minor_sections=16)
    mesh = mesh_from_trimesh(tm, "torus")
    if snap is not None:  # vertices on a grid that float32 still resolves far away
        v = np.round(mesh.vertices.astype(np.float64) / snap) * snap
        mesh = Mesh("torus", v.astype(np.float32), mesh.faces)
    return mesh


def _scene(meshes, instances, centre, size):
    """Camera about 5.7 * size from `centre`; the point light scales with it."""
    c = np.asarray(centre, np.float64)
    eye = c + size * np.array([1.25, 5.0, 2.5])
    return Scene(tuple(meshes), tuple(instances), materials=(Material(albedo=(0.7, 0.6, 0.5)),),
                 camera=Camera(eye=tuple(eye), target=tuple(c), fov_deg=50.0),
                 point_lights=(PointLight(tuple(c + size * np.array([1.0, 3.0, 2.0])),
                                          (10.0 * size**2,) * 3),),
                 directional_lights=(DirectionalLight((-1.0, -2.0, -0.5), (1.0, 1.0, 1.0)),),
                 environment=Environment(radiance=(0.2, 0.25, 0.3)))


def instanced_and_baked(base: Mesh, transforms, centre, size, anchor=(0.0, 0.0, 0.0)):
    """The same geometry twice: instances of `base`, and each instance's vertices moved to
    world space in float64, less `anchor`, stored as float32 in its own mesh placed by a
    translation to `anchor` (the identity when it is 0), keeping instance order so
    closest-hit ties break the same way."""
    inst = _scene([base], [Instance(0, x) for x in transforms], centre, size)
    a = np.asarray(anchor, np.float64)
    baked = []
    for k, x in enumerate(transforms):
        v = base.vertices.astype(np.float64) @ x[:3, :3].T + (x[:3, 3] - a)
        baked.append(Mesh(f"baked{k}", v.astype(np.float32), base.faces))
    world = _scene(baked, [Instance(k, trs(a)) for k in range(len(baked))], centre, size)
    return inst, world


def assert_renders_agree(img, ref, tmp_path, name):
    """Float tolerance for two renders of the same paths through different float32 spaces.

    Embree intersects in local space for one and world space for the other, so hit points
    differ by float32 rounding (~1e-7 relative). Almost every sample is then identical to
    ~1e-6; the rare sample whose shadow ray or bounce ray grazes a silhouette may flip,
    which moves that pixel by up to 1/spp of its value. Hence: the mean absolute difference
    is < 1e-3 of the mean, and >= 99.5% of pixels are within 1e-3 of the image maximum.
    (Measured: mean 2e-8, no pixel beyond 1e-3.) A wrong transform, normal or offset
    fails both by orders of magnitude.
    """
    img, ref = np.asarray(img, np.float64), np.asarray(ref, np.float64)
    diff = np.abs(img - ref)
    mean_rel = diff.mean() / ref.mean()
    within = (diff.max(axis=-1) <= 1e-3 * ref.max()).mean()
    assert ref.max() > 0, "reference is black: the scene is not lit or not seen"
    if not (mean_rel < 1e-3 and within >= 0.995):
        fail_with_images(tmp_path, name, img, ref, diff / (1e-3 * ref.max()),
                         f"{name}: mean |diff| / mean = {mean_rel:.3g} (limit 1e-3), "
                         f"{within:.2%} of pixels within 1e-3 of max (limit 99.5%)")


@pytest.mark.parametrize("case", ["mixed", "tiny", "far"])
def test_instanced_mesh_matches_mesh_baked_into_world_space(tmp_path, case):
    # mixed: several rotated / non-uniformly scaled / moved instances near the origin.
    # tiny: the whole group scaled by 1e-3, camera 1e-3 away. far: the group moved ~1e5
    # with the camera next to it. A mesh stored in float32 world coordinates there is
    # only good to 1/256, and the renderer rightly pushes rays off it by that much, so the
    # far group is baked relative to its centre and placed by a translation: vertices
    # are snapped to 2^-7 so the baked meshes are exact either way.
    anchor = np.zeros(3)
    if case == "far":
        centre, size, base = np.array([98304.0, 65536.0, -81920.0]), 1.0, _torus(2.0**-7)
        anchor = centre
        # 90-degree rotations keep snapped vertices on the grid; translations are on it too.
        placements = [trs(centre), trs(centre + [2.5, 0.25, -1.0], 1.0, (0, 1, 0), 90.0),
                      trs(centre + [-2.0, -0.5, 0.5], 1.0, (1, 0, 0), -90.0)]
    else:
        centre, size, base = np.zeros(3), (1.0 if case == "mixed" else 1e-3), _torus()
        placements = [np.diag([size, size, size, 1.0]) @ x for x in PLACEMENTS]
    inst, world = instanced_and_baked(base, placements, centre, size, anchor)
    assert_renders_agree(render_image(inst, **SETTINGS), render_image(world, **SETTINGS),
                         tmp_path, f"instanced_vs_baked_{case}")


def test_instanced_group_is_translation_invariant_far_from_origin(tmp_path):
    # The torus group (mutual shadows, inter-reflection) and its camera moved by an exact
    # float32 offset: camera rays are identical in local space, every difference comes
    # from the spawned (shadow and bounce) rays.
    centre = np.array([98304.0, 65536.0, -81920.0])
    near = _scene([_torus()], [Instance(0, x) for x in PLACEMENTS], np.zeros(3), 1.0)
    far = _scene([_torus()], [Instance(0, trs(centre) @ x) for x in PLACEMENTS], centre, 1.0)
    assert_renders_agree(render_image(far, **SETTINGS), render_image(near, **SETTINGS),
                         tmp_path, "translated_group")
