"""Shared by the extremes tests (reference and exact K = 3): a small scene with contact
shadows, self-shadowing and every light type, hypothesis strategies for similarity
transforms, and the block z-test "the same image within noise"."""

from __future__ import annotations

import numpy as np
import trimesh
from hypothesis import strategies as st

from nprt.scene.model import DirectionalLight, Environment, Material, PointLight, QuadLight
from nprt.scene.transform import similarity
from nprt.workers.stats.blocks import block_z
from tests.workers.helpers import (
    Camera,
    Instance,
    Scene,
    fail_with_images,
    mesh_from_trimesh,
    plane_mesh,
    trs,
)

Z_LIMIT = 4.0
# Small and quick; 16 spp so a block's noise (about 2 %) leaves drift visible.
SETTINGS = dict(width=32, height=24, spp=16, spp_per_pass=16, bounces=3, shadow_rays=2)
SEEDS = (1, 2)


def small_scene() -> Scene:
    """A torus lying on a tessellated ground, a box with a ball resting on it: contacts,
    self-shadowing and inter-reflection at the scale of the objects, lit by a quad, a
    point and a directional light and a constant environment."""
    ground = plane_mesh(half=3.0, divisions=8, name="ground", material=0)
    torus = mesh_from_trimesh(trimesh.creation.torus(major_radius=0.8, minor_radius=0.25,
                                                     major_sections=24, minor_sections=12),
                              "torus", material=1)
    box = mesh_from_trimesh(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), "box", material=2)
    ball = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=2, radius=0.35), "ball",
                             material=1)
    instances = (Instance(0, np.eye(4)),
                 Instance(1, trs((-0.9, 0.25, 0.3), 1.0, (1, 0, 0), 90.0)),
                 Instance(2, trs((1.0, 0.5, -0.4), 1.0, (0, 1, 0), 25.0)),
                 Instance(3, trs((1.0, 1.35, -0.4))))
    return Scene((ground, torus, box, ball), instances,
                 materials=(Material("ground", (0.6, 0.6, 0.55)),
                            Material("red", (0.75, 0.3, 0.25)),
                            Material("blue", (0.3, 0.4, 0.75))),
                 quad_lights=(QuadLight((-0.5, 3.0, -0.5), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0),
                                        (6.0, 6.0, 5.5)),),
                 point_lights=(PointLight((2.0, 2.5, 2.0), (4.0, 3.5, 3.0)),),
                 directional_lights=(DirectionalLight((-0.5, -1.0, -0.3), (0.8, 0.8, 0.9)),),
                 environment=Environment(radiance=(0.15, 0.17, 0.2)),
                 camera=Camera(eye=(0.5, 2.6, 4.6), target=(0.2, 0.4, 0.0), fov_deg=50.0),
                 name="extremes")


@st.composite
def similarities(draw) -> np.ndarray:
    """x -> s R_y x + t: s from 1e-6 to 1e6, |t| from 0 (or 1) to 1e7 in any direction."""
    scale = 10.0 ** draw(st.floats(-6.0, 6.0))
    far = draw(st.one_of(st.just(0.0), st.floats(0.0, 7.0).map(lambda e: 10.0**e)))
    d = np.array(draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3)))
    d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-3 else np.array([1.0, 0.0, 0.0])
    angle = draw(st.floats(0.0, 360.0))
    return similarity(scale, far * d, angle)


def assert_same_within_noise(tmp_path, name: str, img, ref, ref2) -> None:
    """No 8x8 block of img differs from ref's by more than Z_LIMIT standard errors
    (estimated from ref and ref2, two seeds of the untransformed scene)."""
    z = np.abs(block_z(img, ref, ref2))
    assert np.isfinite(img).all(), f"{name}: non-finite pixels"
    if not (z <= Z_LIMIT).all():
        err = np.kron(z.max(axis=-1), np.ones((8, 8))) / Z_LIMIT  # (h, w), 1 = at the limit
        fail_with_images(tmp_path, name, img, ref, err,
                         f"{name}: {int((z > Z_LIMIT).any(axis=-1).sum())} of "
                         f"{z.shape[0] * z.shape[1]} 8x8 blocks beyond |z| = {Z_LIMIT:g} "
                         f"(max {z.max():.2f})")
