"""`forest:massive`: the forest's species at scale, for scenes that do not fit one node.
Two variants of each species, each tree ~1.35M leaf quads (2.7M triangles, ~140 MB with
its UVs), so the eight base meshes hold over 1 GiB; 10,000 instances on a jittered grid
make ~2.7e10 instanced triangles. Deterministic from the seed and vectorised throughout;
`nprt.scene.store.materialize_demo` writes it once to the scene cache (never to the repo)."""

from __future__ import annotations

import numpy as np

from nprt.scene.demos._common import ground, on_ground, yawed
from nprt.scene.demos.forest import SPECIES, tree_mesh
from nprt.scene.model import Camera, Material, Scene

LEAVES = 1_350_000  # per tree mesh
INSTANCES = 10_000
VARIANTS = 2  # meshes per species
SPACING = 4.0  # m between grid cells
TREE_CFG = dict(sections=16, branches=10)


def build(seed: int, leaves: int = LEAVES, instances: int = INSTANCES,
          name: str = "forest-massive") -> Scene:
    """leaves: leaf quads per tree mesh; instances: trees planted (ground excluded)."""
    materials: list = ["dirt"]  # ALBEDO's, then a textured one per species
    side = int(np.ceil(np.sqrt(instances)))
    half = 0.5 * side * SPACING
    meshes = [ground(half + 25.0, material=0)]
    for s, (species, make, bark, leaf) in enumerate(SPECIES):
        tex = np.array([[bark, leaf]], dtype=np.float32)  # (1, 2, 3) linear
        materials.append(Material(species, leaf, texture=tex))
        for v in range(VARIANTS):
            rng = np.random.default_rng([seed, 11, s, v])
            meshes.append(tree_mesh(f"{species}{v}", make(rng, leaves, TREE_CFG),
                                    len(materials) - 1))
    rng = np.random.default_rng([seed, 12])
    kinds = rng.integers(1, len(meshes), instances)
    cell = np.arange(instances)
    jitter = rng.uniform(-0.3, 0.3, (instances, 2))
    grid = np.column_stack([cell % side, cell // side]) + 0.5 + jitter
    xz = grid * SPACING - half
    pos = np.column_stack([xz[:, 0], np.zeros(instances), xz[:, 1]])
    xf = yawed(rng, pos, (0.8, 1.25))
    return on_ground(name, meshes, kinds, xf, materials,
                     sun=((0.0, half + 20.0), 80.0, 20.0, 3.0), sky_strength=0.9,
                     camera=Camera(eye=(0.0, 14.0, half + 12.0), target=(0.0, 3.0, half - 60.0),
                                   fov_deg=50.0))
