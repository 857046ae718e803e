"""The sculpture demo: three high-poly shapes (sphere, torus, column) heavily displaced along
their normals by a seeded sum of sinusoids, shown on pedestals in a gallery grid.
"""

from __future__ import annotations

import numpy as np
import trimesh

from nprt.scene.demos._common import ground, make_mesh, on_ground, placement
from nprt.scene.model import Camera, Scene

# Per size: icosphere subdivisions, torus (major, minor) and column (around, along) segments,
# gallery grid (columns, rows) and its pitch (m).
SIZES = {
    "default": dict(subdiv=6, torus=(384, 128), column=(160, 320), grid=(6, 4), pitch=2.6),
    "small": dict(subdiv=4, torus=(96, 32), column=(40, 80), grid=(4, 3), pitch=2.6),
    "tiny": dict(subdiv=2, torus=(24, 8), column=(10, 20), grid=(3, 2), pitch=2.6),
}

PEDESTAL = (0.9, 1.0, 0.9)  # width, height, depth (m)
MATERIALS = ("floor", "terracotta", "bronze", "marble", "pedestal")  # ALBEDO's


def build(size: str, seed: int) -> Scene:
    cfg = SIZES[size]
    rng = np.random.default_rng([seed, 3])
    sphere = trimesh.creation.icosphere(subdivisions=cfg["subdiv"], radius=0.7)
    shapes = [
        ("blob", sphere.vertices, sphere.faces, 0.18, 1),
        ("torus", *_torus(0.55, 0.22, *cfg["torus"]), 0.09, 2),
        ("column", *_column(0.3, 1.6, *cfg["column"]), 0.1, 3),
    ]
    meshes = [ground(40.0, material=0)]
    for name, v, f, amplitude, mat in shapes:
        f = _outward(v, f)
        dv, normals = _displace(rng, v, f, amplitude)
        meshes.append(make_mesh(name, dv, f, mat, normals=normals))
    box = trimesh.creation.box(extents=PEDESTAL)
    meshes.append(make_mesh("pedestal", box.vertices + [0, PEDESTAL[1] / 2, 0], box.faces, 4))

    nx, nz = cfg["grid"]
    gx, gz = np.meshgrid((np.arange(nx) - (nx - 1) / 2) * cfg["pitch"],
                         (np.arange(nz) - (nz - 1) / 2) * cfg["pitch"], indexing="ij")
    n = nx * nz
    base = np.column_stack([gx.ravel(), np.zeros(n), gz.ravel()])
    kinds = 1 + np.arange(n) % 3
    rng.shuffle(kinds)
    rot = _random_rotations(rng, n)
    s = rng.uniform(0.9, 1.3, n)
    xf = np.zeros((n, 4, 4))
    xf[:, :3, :3] = rot * s[:, None, None]
    xf[:, 3, 3] = 1.0
    # Rest each sculpture exactly on its pedestal: lowest vertex after rotation and scale.
    lowest = np.array([(meshes[k].vertices.astype(np.float64) @ xf[i, 1, :3]).min()
                       for i, k in enumerate(kinds)])
    xf[:, :3, 3] = base + np.column_stack([np.zeros(n), PEDESTAL[1] - lowest, np.zeros(n)])
    pedestals = placement(rng.uniform(0, np.pi, n), np.ones((n, 3)), base)
    pedestal_mesh = len(meshes) - 1
    extent = 0.5 * cfg["pitch"] * max(nx, nz)
    return on_ground(f"sculpture-{size}", meshes, np.r_[kinds, np.full(n, pedestal_mesh)],
                     np.concatenate([xf, pedestals]), MATERIALS,
                     sun=((2.0, 3.0), 14.0, 4.0, 4.0), sky_strength=0.7,
                     camera=Camera(eye=(0.35 * extent, 2.5 + 0.5 * extent, 1.9 * extent + 3.0),
                                   target=(0.0, 1.0, 0.0), fov_deg=42.0))


def _displace(rng, v: np.ndarray, f: np.ndarray, amplitude: float):
    """Push vertices along their normals by a sum of 10 random sinusoids (octaves 2..14).

    v : (n, 3) float64, f : (m, 3) -> displaced vertices (n, 3), new normals (n, 3)
    """
    normals = trimesh.Trimesh(v, f, process=False).vertex_normals
    freq = rng.normal(size=(10, 3))
    freq *= (np.geomspace(2.0, 14.0, 10) / np.linalg.norm(freq, axis=1))[:, None]
    phase = rng.uniform(0, 2 * np.pi, 10)
    weight = 1.0 / np.sqrt(np.arange(1, 11))
    height = np.sin(v @ freq.T + phase) @ weight / weight.sum()  # (n,) in [-1, 1]
    out = v + amplitude * 2.0 * height[:, None] * normals
    return out, trimesh.Trimesh(out, f, process=False).vertex_normals


def _outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Wind a closed mesh's faces so its normals point outwards (positive volume)."""
    return f if trimesh.Trimesh(v, f, process=False).volume > 0 else f[:, ::-1].copy()


def _torus(major: float, minor: float, n_major: int, n_minor: int):
    """A closed torus around +y as a (n_major x n_minor) quad grid."""
    a = 2 * np.pi * np.arange(n_major) / n_major
    b = 2 * np.pi * np.arange(n_minor) / n_minor
    aa, bb = np.meshgrid(a, b, indexing="ij")
    r = major + minor * np.cos(bb)
    v = np.stack([r * np.cos(aa), minor * np.sin(bb), r * np.sin(aa)], -1).reshape(-1, 3)
    return v, _grid_faces(n_major, n_minor, wrap_j=True)


def _column(radius: float, height: float, n_around: int, n_along: int):
    """A capped cylinder from y=-h/2 to h/2, as an (n_along x n_around) ring grid + fans."""
    a = -2 * np.pi * np.arange(n_around) / n_around
    y = np.linspace(-height / 2, height / 2, n_along)
    yy, aa = np.meshgrid(y, a, indexing="ij")
    side = np.stack([radius * np.cos(aa), yy, radius * np.sin(aa)], -1).reshape(-1, 3)
    faces = _grid_faces(n_along, n_around, wrap_i=False, wrap_j=True)
    n = len(side)
    caps = np.array([[0.0, -height / 2, 0.0], [0.0, height / 2, 0.0]])
    k = np.arange(n_around)
    k1 = (k + 1) % n_around
    bottom = np.column_stack([np.full(n_around, n), k1, k])
    top = np.column_stack([np.full(n_around, n + 1), (n_along - 1) * n_around + k,
                           (n_along - 1) * n_around + k1])
    return np.vstack([side, caps]), np.vstack([faces, bottom, top])


def _grid_faces(ni: int, nj: int, wrap_i: bool = True, wrap_j: bool = True) -> np.ndarray:
    """Two triangles per cell of an (ni x nj) vertex grid, row-major, optionally wrapping."""
    i = np.arange(ni if wrap_i else ni - 1)
    j = np.arange(nj if wrap_j else nj - 1)
    ii, jj = np.meshgrid(i, j, indexing="ij")
    i1, j1 = (ii + 1) % ni, (jj + 1) % nj
    a, b, c, d = ii * nj + jj, i1 * nj + jj, i1 * nj + j1, ii * nj + j1
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                           np.stack([a, c, d], -1).reshape(-1, 3)])


def _random_rotations(rng, n: int) -> np.ndarray:
    """(n, 3, 3) uniformly random rotations (from normalised Gaussian quaternions)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.stack([trimesh.transformations.quaternion_matrix(x)[:3, :3] for x in q])
