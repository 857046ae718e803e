"""The forest demo: four tree species made of a trunk, branches and thousands of small leaf
quads (thin, high-frequency geometry), scattered with overlapping crowns on a ground plane.
"""

from __future__ import annotations

import numpy as np

from nprt.scene.demos._common import (
    concat,
    ground,
    on_ground,
    quads,
    random_frames,
    scatter,
    tube,
    yawed,
)
from nprt.scene.model import VERTEX_DTYPE, Camera, Material, Mesh, Scene

# Per size: leaves per species (oak, pine, birch, bush), instances per species, half extent
# of the planted square (m), trunk sections, branches per tree.
SIZES = {
    "default": dict(leaves=(16000, 20000, 12000, 5000), counts=(22, 22, 16, 24),
                    half=35.0, sections=16, branches=10),
    "small": dict(leaves=(1200, 1500, 1000, 400), counts=(10, 10, 8, 10),
                  half=22.0, sections=10, branches=5),
    "tiny": dict(leaves=(80, 100, 60, 30), counts=(2, 2, 2, 2),
                 half=8.0, sections=6, branches=2),
}

# The bark | leaf texture: UVs at the two texel centres pick a colour under any filtering.
BARK_UV, LEAF_UV = (0.25, 0.5), (0.75, 0.5)


def build(size: str, seed: int) -> Scene:
    if size == "massive":
        from nprt.scene.demos import massive

        return massive.build(seed)
    cfg = SIZES[size]
    rng = np.random.default_rng([seed, 1])
    materials: list = ["dirt"]  # ALBEDO's, then a textured one per species
    meshes = [ground(cfg["half"] + 25.0, material=0)]
    for (name, make, bark, leaf), n_leaves in zip(SPECIES, cfg["leaves"], strict=True):
        tex = np.array([[bark, leaf]], dtype=np.float32)  # (1, 2, 3) linear
        materials.append(Material(name, leaf, texture=tex))
        meshes.append(tree_mesh(name, make(rng, n_leaves, cfg), len(materials) - 1))

    kinds = np.repeat(np.arange(1, 5), cfg["counts"])
    rng.shuffle(kinds)
    xz = scatter(rng, len(kinds), cfg["half"], min_dist=2.5)
    n = len(kinds)
    pos = np.column_stack([xz[:, 0], np.zeros(n), xz[:, 1]])
    xf = yawed(rng, pos, (0.8, 1.25))
    half = cfg["half"]
    return on_ground(f"forest-{size}", meshes, kinds, xf, materials,
                     sun=((0.4 * half, 0.3 * half), 60.0, 14.0, 3.0), sky_strength=0.9,
                     camera=Camera(eye=(0.0, 7.0 + 0.1 * half, half + 12.0),
                                   target=(0.0, 3.5, -0.2 * half), fov_deg=50.0))


def tree_mesh(name: str, parts: tuple[list, list], material: int) -> Mesh:
    """parts: (bark parts, leaf parts), each a list of (vertices, faces)."""
    bark, leaf = parts
    groups = [p for p in (bark, leaf) if p]
    uv_rows = [BARK_UV, LEAF_UV] if bark else [LEAF_UV]
    merged = [concat(g) for g in groups]
    v, f = concat(merged)
    uvs = np.concatenate([np.tile(uv, (len(m[0]), 1)) for m, uv in zip(merged, uv_rows,
                                                                        strict=True)])
    return Mesh(name, v.astype(VERTEX_DTYPE), f.astype(np.uint32), None,
                uvs.astype(VERTEX_DTYPE), material)


def _leaves(rng, centres: np.ndarray, width: float, height: float):
    """Randomly oriented leaf quads. centres : (n, 3) float64 -> (vertices, faces)."""
    n = len(centres)
    t, b = random_frames(rng, n)
    jitter = rng.uniform(0.7, 1.3, size=(n, 1, 1))
    su = np.array([-0.5, 0.5, 0.5, -0.5])[None, :, None] * width * jitter
    sv = np.array([-0.5, -0.5, 0.5, 0.5])[None, :, None] * height * jitter
    return quads(centres[:, None, :] + su * t[:, None, :] + sv * b[:, None, :])


def _in_ellipsoid(rng, n: int, centre, radii, shell: float = 0.25) -> np.ndarray:
    """n points in an ellipsoid, biased to its surface (r ~ u**shell). -> (n, 3) float64."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0, 1, size=(n, 1)) ** shell
    return np.asarray(centre) + d * r * np.asarray(radii)


def _branches(rng, n: int, base_y: tuple[float, float], tips: np.ndarray, sections: int,
              r0: float, r1: float) -> list:
    ys = rng.uniform(*base_y, size=n)
    return [tube((0.0, y, 0.0), tip, r0, r1, sections) for y, tip in zip(ys, tips, strict=True)]


def _oak(rng, n_leaves: int, cfg: dict):
    sec, nb = cfg["sections"], cfg["branches"]
    centre, radii = (0.0, 5.2, 0.0), (2.6, 2.0, 2.6)
    tips = _in_ellipsoid(rng, nb, centre, np.array(radii) * 0.7, shell=0.1)
    bark = [tube((0, 0, 0), (0, 3.4, 0), 0.32, 0.2, sec)]
    bark += _branches(rng, nb, (2.4, 3.3), tips, max(4, sec // 2), 0.12, 0.04)
    leaf = [_leaves(rng, _in_ellipsoid(rng, n_leaves, centre, radii), 0.22, 0.16)]
    return bark, leaf


def _pine(rng, n_leaves: int, cfg: dict):
    sec, nb = cfg["sections"], cfg["branches"]
    y = 1.8 + 8.2 * rng.uniform(0, 1, n_leaves) ** 0.8
    radius = 2.3 * (1.0 - (y - 1.8) / 8.6) * np.sqrt(rng.uniform(0.05, 1, n_leaves))
    ang = rng.uniform(0, 2 * np.pi, n_leaves)
    needles = np.column_stack([radius * np.cos(ang), y, radius * np.sin(ang)])
    by = np.linspace(2.0, 8.5, nb)
    ba = rng.uniform(0, 2 * np.pi, nb)
    br = 2.0 * (1.0 - (by - 1.8) / 8.6)
    tips = np.column_stack([br * np.cos(ba), by - 0.4, br * np.sin(ba)])
    bark = [tube((0, 0, 0), (0, 10.0, 0), 0.26, 0.04, sec)]
    bark += [tube((0, yy, 0), tip, 0.06, 0.02, max(4, sec // 2)) for yy, tip in zip(by, tips,
                                                                                 strict=True)]
    leaf = [_leaves(rng, needles, 0.36, 0.03)]
    return bark, leaf


def _birch(rng, n_leaves: int, cfg: dict):
    sec, nb = cfg["sections"], cfg["branches"]
    clumps = np.array([[0.6, 6.0, 0.2], [-0.5, 7.2, -0.3], [0.1, 8.3, 0.4], [-0.2, 5.2, -0.6]])
    owner = rng.integers(0, len(clumps), n_leaves)
    pts = _in_ellipsoid(rng, n_leaves, (0, 0, 0), (1.2, 0.9, 1.2), shell=0.4) + clumps[owner]
    bark = [tube((0, 0, 0), (0, 8.8, 0), 0.16, 0.05, sec)]
    bark += _branches(rng, nb, (4.0, 7.5), clumps[np.arange(nb) % len(clumps)],
                      max(4, sec // 2), 0.06, 0.02)
    leaf = [_leaves(rng, pts, 0.14, 0.10)]
    return bark, leaf


def _bush(rng, n_leaves: int, cfg: dict):
    pts = _in_ellipsoid(rng, n_leaves, (0.0, 0.7, 0.0), (1.2, 0.7, 1.2), shell=0.3)
    pts[:, 1] = np.maximum(pts[:, 1], 0.25)  # keep every leaf above the ground
    return [], [_leaves(rng, pts, 0.2, 0.14)]


# (name, builder, bark colour, leaf colour) of each species, in mesh order.
SPECIES = (
    ("oak", _oak, (0.30, 0.20, 0.12), (0.18, 0.36, 0.08)),
    ("pine", _pine, (0.28, 0.18, 0.10), (0.07, 0.22, 0.09)),
    ("birch", _birch, (0.75, 0.72, 0.66), (0.36, 0.52, 0.12)),
    ("bush", _bush, (0.25, 0.18, 0.10), (0.20, 0.40, 0.10)),
)
