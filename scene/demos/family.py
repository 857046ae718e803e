"""A test family of meshes the proxy defaults were not tuned on, and a scene of them whose
instance boxes overlap heavily: foliage clusters (random leaf quads around a trunk), thin
shells, meshes with holes and interpenetrating parts. Deterministic from a seed.

Not a demo (DEMOS lists those); `build` gives the scene, `family_meshes` the meshes alone.
`build_foliage` is a second scene kept out of every default's tuning: leaf clouds of thousands
of small quads, each mesh heavier than the widest proxy (so the policy cannot replicate it),
in interpenetrating instances, with finely tessellated rocks under a sun and sky.
"""

from __future__ import annotations

import numpy as np
import trimesh

from nprt.scene.demos._common import (
    concat,
    ground,
    make_mesh,
    on_ground,
    placement,
    quads,
    random_frames,
    tube,
    yawed,
)
from nprt.scene.model import Camera, Material, Mesh, Scene, instance_world_bounds

# Per size: leaves of the two foliage clusters, sphere subdivisions (shell, holes), instances
# per family mesh and the half extent of the patch they are packed into (boxes overlap).
SIZES = {
    "default": dict(leaves=(3000, 1200), subdiv=4, copies=12, half=9.0),
    "small": dict(leaves=(1500, 600), subdiv=4, copies=6, half=6.0),
    "tiny": dict(leaves=(400, 200), subdiv=3, copies=3, half=4.0),
}
MESHES = ("foliage", "sparse_foliage", "shell", "holes", "rings")


def _foliage(rng, n_leaves: int, name: str, leaf: float) -> Mesh:
    """A trunk and n_leaves random leaf quads in a crown around it: thin, random geometry."""
    d = rng.normal(size=(n_leaves, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0, 1, size=(n_leaves, 1)) ** 0.4
    centres = np.array([0.0, 2.0, 0.0]) + d * r * np.array([1.3, 1.0, 1.3])
    t, b = random_frames(rng, n_leaves)
    su = np.array([-0.5, 0.5, 0.5, -0.5])[None, :, None] * leaf
    sv = np.array([-0.5, -0.5, 0.5, 0.5])[None, :, None] * 0.7 * leaf
    leaves = quads(centres[:, None, :] + su * t[:, None, :] + sv * b[:, None, :])
    v, f = concat([tube((0, 0, 0), (0, 2.2, 0), 0.12, 0.05, 8), leaves])
    return make_mesh(name, v, f, material=1)


def _shell(subdiv: int) -> Mesh:
    """An open hemispherical bowl with a wall 1 % of its radius thick (inner and outer
    surface, no rim): a thin shell whose two sides are close but distinct."""
    s = trimesh.creation.icosphere(subdivisions=subdiv)
    keep = s.vertices[s.faces].mean(axis=1)[:, 1] < 0.15  # lower half and a little more
    outer = (s.vertices, s.faces[keep])
    inner = (0.99 * s.vertices, s.faces[keep][:, ::-1])
    v, f = concat([outer, inner])
    return make_mesh("shell", v, f, material=2)


def _holes(rng, subdiv: int) -> Mesh:
    """A sphere with a third of its surface cut away in round patches: one sees through it
    into its own inside."""
    s = trimesh.creation.icosphere(subdivisions=subdiv)
    c = s.vertices[s.faces].mean(axis=1)
    centres = rng.normal(size=(14, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    near = np.max(c @ centres.T, axis=1) > 0.9  # within ~25 degrees of a hole centre
    return make_mesh("holes", s.vertices, s.faces[~near], material=2)


def _rings() -> Mesh:
    """Three interpenetrating tori on orthogonal axes (parts that pass through each other)."""
    parts = []
    for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
        tor = trimesh.creation.torus(major_radius=1.0, minor_radius=0.12, major_sections=48,
                                     minor_sections=12)
        rot = trimesh.geometry.align_vectors((0, 0, 1), axis)
        tor.apply_transform(rot)
        parts.append((tor.vertices, tor.faces))
    v, f = concat(parts)
    return make_mesh("rings", v, f, material=2)


def family_meshes(size: str = "small", seed: int = 0) -> list[Mesh]:
    """The family's meshes in MESHES order, deterministic in (size, seed)."""
    cfg = SIZES[size]
    rng = np.random.default_rng([seed, 11])
    dense, sparse = cfg["leaves"]
    return [_foliage(rng, dense, "foliage", 0.2), _foliage(rng, sparse, "sparse_foliage", 0.3),
            _shell(cfg["subdiv"]), _holes(rng, cfg["subdiv"]), _rings()]


def build(size: str = "small", seed: int = 0) -> Scene:
    """Family meshes packed so tightly that most instance boxes overlap others (crowns
    interpenetrate), on a ground; instance 0 is the ground."""
    cfg = SIZES[size]
    rng = np.random.default_rng([seed, 12])
    materials = ("dirt", "leaf", Material("stone", (0.55, 0.52, 0.48)))
    meshes = [ground(cfg["half"] + 10.0, material=0), *family_meshes(size, seed)]
    kinds = np.repeat(np.arange(1, len(meshes)), cfg["copies"])
    rng.shuffle(kinds)
    n = len(kinds)
    # Spacing below the crowns' 2.6 m width: neighbours' boxes overlap and their geometry
    # interpenetrates, the case where a box entry says least about the first hit.
    pos = np.column_stack([rng.uniform(-cfg["half"], cfg["half"], n),
                           np.where(kinds >= 3, 1.0, 0.0),  # shells and rings sit above ground
                           rng.uniform(-cfg["half"], cfg["half"], n)])
    xf = yawed(rng, pos, (0.8, 1.3))
    half = cfg["half"]
    return on_ground(f"family-{size}", meshes, kinds, xf, materials,
                     sun=((0.3 * half, 0.2 * half), 40.0, 10.0, 3.0), sky_strength=0.9,
                     camera=Camera(eye=(0.0, 4.0 + 0.3 * half, half + 8.0),
                                   target=(0.0, 1.5, 0.0), fov_deg=50.0))


def overlap_fraction(scene: Scene) -> float:
    """Share of non-ground instances whose world box overlaps another non-ground one's."""
    boxes = instance_world_bounds(scene)[1:]  # (m, 2, 3)
    lo, hi = boxes[:, 0], boxes[:, 1]
    inter = np.all((lo[:, None] < hi[None]) & (lo[None] < hi[:, None]), axis=2)
    np.fill_diagonal(inter, False)
    return float(inter.any(axis=1).mean())


# Per size: leaves of the two tree meshes (72 bytes a leaf: every mesh but "tiny"'s outweighs
# a width-64 proxy, about 163 kB), rock subdivisions, trees and rocks, half extent of the
# patch. "tiny" is for tests, with width 16 forced (a 22 kB proxy).
FOLIAGE_SIZES = {
    "default": dict(leaves=(8000, 5000), subdiv=5, trees=14, rocks=5, half=5.0),
    "small": dict(leaves=(3000, 2500), subdiv=5, trees=8, rocks=3, half=3.5),
    "tiny": dict(leaves=(800, 500), subdiv=3, trees=4, rocks=2, half=2.0),
}
FOLIAGE_MESHES = ("leafy", "leafy_sparse", "rock")


def _rock(rng, subdiv: int) -> Mesh:
    """A finely tessellated icosphere, squashed and displaced by a few random waves."""
    s = trimesh.creation.icosphere(subdivisions=subdiv)
    v = np.asarray(s.vertices, np.float64)
    k = rng.normal(size=(6, 3)) * 2.5
    bump = 0.08 * np.sin(v @ k.T + rng.uniform(0, 2 * np.pi, 6)).sum(axis=1)
    v = v * (1.0 + bump)[:, None] * np.array([0.9, 0.55, 0.8])
    return make_mesh("rock", v + np.array([0.0, 0.3, 0.0]), s.faces, material=2)


def foliage_meshes(size: str = "small", seed: int = 0) -> list[Mesh]:
    """The foliage scene's meshes in FOLIAGE_MESHES order, deterministic in (size, seed)."""
    cfg = FOLIAGE_SIZES[size]
    rng = np.random.default_rng([seed, 21])
    dense, sparse = cfg["leaves"]
    return [_foliage(rng, dense, "leafy", 0.05), _foliage(rng, sparse, "leafy_sparse", 0.06),
            _rock(rng, cfg["subdiv"])]


def build_foliage(size: str = "small", seed: int = 0) -> Scene:
    """Trees of two leaf-cloud meshes whose crowns interpenetrate, rocks among them, a ground,
    sun and sky; instance 0 is the ground."""
    cfg = FOLIAGE_SIZES[size]
    rng = np.random.default_rng([seed, 22])
    half = cfg["half"]
    materials = ("dirt", "leaf", Material("stone", (0.50, 0.48, 0.45)))
    meshes = [ground(half + 10.0, material=0), *foliage_meshes(size, seed)]
    kinds = np.r_[np.arange(cfg["trees"]) % 2 + 1, np.full(cfg["rocks"], 3)]
    n = len(kinds)
    pos = np.column_stack([rng.uniform(-half, half, n), np.zeros(n), rng.uniform(-half, half, n)])
    s = np.where(kinds == 3, rng.uniform(0.5, 0.9, n), rng.uniform(0.9, 1.4, n))
    xf = placement(rng.uniform(0, 2 * np.pi, n), np.repeat(s[:, None], 3, 1), pos)
    return on_ground(f"foliage-{size}", meshes, kinds, xf, materials,
                     sun=((0.4 * half, 0.3 * half), 30.0, 8.0, 3.0), sky_strength=0.8,
                     camera=Camera(eye=(0.0, 3.0 + 0.3 * half, half + 7.0),
                                   target=(0.0, 1.6, 0.0), fov_deg=50.0))
