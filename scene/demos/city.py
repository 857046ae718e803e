"""The city demo: eleven building designs (boxes, set-backs, polygonal towers) whose facades
carry one recessed window per bay, placed on a grid of lots with overlapping bounds.
"""

from __future__ import annotations

import numpy as np
import trimesh

from nprt.scene.demos._common import concat, ground, make_mesh, on_ground, placement, quads
from nprt.scene.model import Camera, Scene

# Per size: window bay width and storey height (m), lots per side (x, z), lot pitch (m).
SIZES = {
    "default": dict(bay=0.8, storey=2.0, lots=(8, 8), pitch=21.0),
    "small": dict(bay=3.0, storey=5.0, lots=(5, 5), pitch=21.0),
    "tiny": dict(bay=9.0, storey=14.0, lots=(4, 3), pitch=21.0),
}

# Blocks: ("box", cx, cz, width, depth, y0, height) or ("poly", cx, cz, radius, sides, y0, height).
# Window fraction of a bay (width, height) and material index per design.
DESIGNS = [
    ("slab", [("box", 0, 0, 16, 9, 0, 24)], (0.7, 0.5), 1),
    ("tower", [("box", 0, 0, 12, 12, 0, 54)], (0.6, 0.6), 4),
    ("podium", [("box", 0, 0, 18, 18, 0, 10), ("box", 0, 0, 10, 10, 10, 40)], (0.75, 0.55), 2),
    ("stepped", [("box", 0, 0, 16, 16, 0, 16), ("box", 0, 0, 12, 12, 16, 14),
                 ("box", 0, 0, 8, 8, 30, 12)], (0.5, 0.5), 3),
    ("octagon", [("poly", 0, 0, 7, 8, 0, 42)], (0.8, 0.7), 4),
    ("ell", [("box", -1, 4, 14, 6, 0, 20), ("box", -5, -3, 6, 8, 0, 20)], (0.45, 0.5), 1),
    ("lowrise", [("box", 0, 0, 18, 14, 0, 8)], (0.9, 0.6), 5),
    ("twins", [("box", 0, 0, 18, 10, 0, 8), ("box", -4.5, 0, 7, 7, 8, 30),
               ("box", 4.5, 0, 7, 7, 8, 36)], (0.6, 0.5), 2),
    ("hexa", [("poly", 0, 0, 8, 6, 0, 28), ("poly", 0, 0, 5, 6, 28, 8)], (0.7, 0.6), 3),
    ("needle", [("box", 0, 0, 8, 8, 0, 66)], (0.55, 0.65), 5),
    ("midrise", [("box", 0, 0, 16, 12, 0, 30), ("box", 0, -2, 16, 8, 30, 6)], (0.5, 0.45), 1),
]

MATERIALS = ("asphalt", "concrete", "brick", "sandstone", "blue-glass", "white")  # ALBEDO's

# One bay: 4 outer corners, 4 window corners, 4 recessed corners; 9 quads facing out.
BAY_QUADS = np.array([[0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7],  # wall ring
                      [4, 5, 9, 8], [5, 6, 10, 9], [6, 7, 11, 10], [7, 4, 8, 11],  # reveal
                      [8, 9, 10, 11]])  # glass
WINDOW_DEPTH = 0.25


def build(size: str, seed: int) -> Scene:
    cfg = SIZES[size]
    rng = np.random.default_rng([seed, 2])
    meshes = [ground(2.0 * cfg["pitch"] * max(cfg["lots"]), material=0)]
    for name, blocks, win, mat in DESIGNS:
        v, f = _building(rng, blocks, win, cfg["bay"], cfg["storey"])
        meshes.append(make_mesh(name, v, f, mat))

    nx, nz = cfg["lots"]
    gx, gz = np.meshgrid((np.arange(nx) - (nx - 1) / 2) * cfg["pitch"],
                         (np.arange(nz) - (nz - 1) / 2) * cfg["pitch"], indexing="ij")
    n = nx * nz
    # Every design at least once, the rest drawn at random.
    kinds = np.concatenate([np.arange(len(DESIGNS)), rng.integers(0, len(DESIGNS), n)])[:n]
    rng.shuffle(kinds)
    yaw = rng.integers(0, 4, n) * (np.pi / 2) + rng.uniform(-0.3, 0.3, n)
    sxz = rng.uniform(0.85, 1.1, n)
    scale = np.column_stack([sxz, rng.uniform(0.8, 1.25, n), sxz])
    jitter = rng.uniform(-1.5, 1.5, size=(n, 2))
    pos = np.column_stack([gx.ravel() + jitter[:, 0], np.zeros(n), gz.ravel() + jitter[:, 1]])
    xf = placement(yaw, scale, pos)
    half = 0.5 * cfg["pitch"] * max(cfg["lots"])
    return on_ground(f"city-{size}", meshes, kinds + 1, xf, MATERIALS,  # mesh 0: the ground
                     sun=((0.5 * half, 0.3 * half), 160.0, 30.0, 3.0), sky_strength=1.0,
                     camera=Camera(eye=(1.3 * half, 0.85 * half + 25.0, 1.65 * half),
                                   target=(0.0, 10.0, 0.0), fov_deg=45.0))


def _building(rng, blocks: list, win: tuple[float, float], bay: float, storey: float):
    parts = []
    for kind, cx, cz, a, b, y0, h in blocks:
        if kind == "box":
            w, d = a, b
            x0, x1, z0, z1 = cx - w / 2, cx + w / 2, cz - d / 2, cz + d / 2
            # (origin, u direction, width) per side; the wall faces cross(u, +y), outwards.
            sides = [((x0, z1), (1, 0), w), ((x1, z1), (0, -1), d),
                     ((x1, z0), (-1, 0), w), ((x0, z0), (0, 1), d)]
            roof = np.array([[[x0, y0 + h, z1], [x1, y0 + h, z1], [x1, y0 + h, z0],
                              [x0, y0 + h, z0]]])
            parts.append(quads(roof))
        else:
            radius, n_sides = a, int(b)
            ang = -2.0 * np.pi * np.arange(n_sides + 1) / n_sides  # clockwise from above
            ring = np.column_stack([cx + radius * np.cos(ang), cz + radius * np.sin(ang)])
            sides = [(tuple(ring[k]), tuple((ring[k + 1] - ring[k]) / np.linalg.norm(
                ring[k + 1] - ring[k])), float(np.linalg.norm(ring[k + 1] - ring[k])))
                for k in range(n_sides)]
            parts.append(_fan_roof(ring[:-1], (cx, cz), y0 + h))
        for (ox, oz), (ux, uz), width in sides:
            parts.append(_facade(np.array([ox, y0, oz]), np.array([ux, 0.0, uz]), width, h,
                                 bay, storey, win))
    top = blocks[-1]
    for _ in range(2):  # rooftop plant boxes
        ext = rng.uniform([1.0, 0.8, 1.0], [3.0, 2.0, 3.0])
        off = rng.uniform(-1.5, 1.5, size=2)
        box = trimesh.creation.box(extents=ext)
        lift = np.array([top[1] + off[0], top[5] + top[6] + ext[1] / 2, top[2] + off[1]])
        parts.append((box.vertices + lift, box.faces))
    return concat(parts)


def _fan_roof(ring: np.ndarray, centre, y: float):
    """ring : (n, 2) clockwise from above -> roof triangles facing +y."""
    n = len(ring)
    v = np.vstack([[centre[0], y, centre[1]], np.column_stack([ring[:, 0], np.full(n, y),
                                                                ring[:, 1]])])
    k = np.arange(n)
    return v, np.column_stack([np.zeros(n, dtype=np.int64), 1 + k, 1 + (k + 1) % n])


def _facade(origin, u_dir, width: float, height: float, bay: float, storey: float, win):
    """A wall spanned by u_dir and +y with one recessed window per bay.

    origin : (3,) float64 bottom-left corner, u_dir : (3,) unit horizontal
    returns : vertices (12 c, 3) float64, faces (18 c, 3) int64 for c bays
    """
    nc, nr = max(1, round(width / bay)), max(1, round(height / storey))
    cw, ch = width / nc, height / nr
    mx = 0.5 * cw * (1.0 - win[0])
    y0 = 0.4 * ch * (1.0 - win[1])
    y1 = y0 + ch * win[1]
    d = WINDOW_DEPTH
    tpl = np.array([[0, 0, 0], [cw, 0, 0], [cw, ch, 0], [0, ch, 0],
                    [mx, y0, 0], [cw - mx, y0, 0], [cw - mx, y1, 0], [mx, y1, 0],
                    [mx, y0, -d], [cw - mx, y0, -d], [cw - mx, y1, -d], [mx, y1, -d]])
    ju, iv = np.meshgrid(np.arange(nc), np.arange(nr), indexing="ij")
    offs = np.column_stack([ju.ravel() * cw, iv.ravel() * ch, np.zeros(nc * nr)])
    local = tpl[None] + offs[:, None, :]  # (c, 12, 3) in (u, v, w)
    normal = np.cross(u_dir, [0.0, 1.0, 0.0])
    basis = np.stack([u_dir, [0.0, 1.0, 0.0], normal])  # rows: u, v, w in world
    verts = origin + local.reshape(-1, 3) @ basis
    tris = np.concatenate([BAY_QUADS[:, [0, 1, 2]], BAY_QUADS[:, [0, 2, 3]]])  # (18, 3)
    faces = (tris[None] + 12 * np.arange(nc * nr)[:, None, None]).reshape(-1, 3)
    return verts, faces
