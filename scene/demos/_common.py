"""Building blocks shared by the demo scenes: quads, cylinders, placements, sky and sun panel,
the named materials, and a scene on a ground."""

from __future__ import annotations

import numpy as np

from nprt.scene.model import (
    INDEX_DTYPE,
    TRANSFORM_DTYPE,
    VERTEX_DTYPE,
    Camera,
    Environment,
    Instances,
    Material,
    Mesh,
    QuadLight,
    Scene,
)

QUAD_TRIS = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)

# Albedo (linear RGB) of the demos' plain materials, by name: one table for every demo.
ALBEDO = {
    "dirt": (0.30, 0.24, 0.16), "leaf": (0.20, 0.42, 0.10), "asphalt": (0.18, 0.18, 0.19),
    "concrete": (0.60, 0.58, 0.55), "brick": (0.50, 0.28, 0.20), "sandstone": (0.70, 0.62, 0.48),
    "blue-glass": (0.25, 0.32, 0.40), "white": (0.80, 0.80, 0.78), "floor": (0.45, 0.43, 0.40),
    "terracotta": (0.65, 0.33, 0.20), "bronze": (0.45, 0.32, 0.15), "marble": (0.85, 0.84, 0.80),
    "pedestal": (0.25, 0.25, 0.27),
}


def on_ground(name: str, meshes, kinds: np.ndarray, xf: np.ndarray, materials, *, sun: tuple,
              sky_strength: float, camera: Camera) -> Scene:
    """An outdoor demo: meshes[0] is the ground, instance 0 (identity); kinds (n,) the
    meshes of the others, placed by xf (n, 4, 4). materials: a Material or the name of a
    plain one in ALBEDO each. Lit by sun_panel(*sun) and sky(sky_strength)."""
    mats = tuple(m if isinstance(m, Material) else Material(m, ALBEDO[m]) for m in materials)
    return Scene(meshes=tuple(meshes),
                 instances=Instances(np.r_[0, kinds], np.concatenate([np.eye(4)[None], xf])),
                 materials=mats, quad_lights=(sun_panel(*sun),),
                 environment=sky(sky_strength), camera=camera, name=name)


def quads(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent quads as two triangles each, wound 0-1-2 / 0-2-3.

    corners : (n, 4, 3) float64
    returns : vertices (4n, 3) float64, faces (2n, 3) int64
    """
    n = len(corners)
    faces = (QUAD_TRIS[None] + 4 * np.arange(n)[:, None, None]).reshape(-1, 3)
    return corners.reshape(-1, 3), faces


def concat(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Merge (vertices (v, 3), faces (f, 3)) parts into one indexed mesh."""
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)])
    return vertices, faces


def tube(p0, p1, r0: float, r1: float, sections: int) -> tuple[np.ndarray, np.ndarray]:
    """Open tapered tube from p0 (radius r0) to p1 (radius r1); vertices (2s, 3), faces (2s, 3)."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    ang = 2.0 * np.pi * np.arange(sections) / sections
    ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w  # (s, 3)
    vertices = np.concatenate([p0 + r0 * ring, p1 + r1 * ring])
    i = np.arange(sections)
    j = (i + 1) % sections
    faces = np.concatenate([np.stack([i, j, j + sections], 1), np.stack([i, j + sections,
                                                                         i + sections], 1)])
    return vertices, faces


def random_frames(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Random orthonormal tangent pairs (t, b), each (n, 3) float64, for orienting quads."""
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t = np.cross(normal, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(normal, t)


def make_mesh(name: str, vertices, faces, material: int, normals=None) -> Mesh:
    """Cast to the model's dtypes (float32 vertices, uint32 faces)."""
    n = None if normals is None else np.ascontiguousarray(normals, dtype=VERTEX_DTYPE)
    return Mesh(name, np.ascontiguousarray(vertices, dtype=VERTEX_DTYPE),
                np.ascontiguousarray(faces, dtype=INDEX_DTYPE), n, None, material)


def ground(half_size: float, material: int, y: float = 0.0) -> Mesh:
    """A square ground quad at height y, facing +y, with upward normals."""
    h = half_size
    corners = np.array([[[-h, y, h], [h, y, h], [h, y, -h], [-h, y, -h]]])
    v, f = quads(corners)
    return make_mesh("ground", v, f, material, normals=np.tile([0.0, 1.0, 0.0], (4, 1)))


def placement(yaw: np.ndarray, scale: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """T @ Ry(yaw) @ S per instance.

    yaw : (n,) radians, scale : (n, 3), pos : (n, 3) -> (n, 4, 4) float64
    """
    n = len(yaw)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0], rot[:, 0, 2], rot[:, 1, 1], rot[:, 2, 0], rot[:, 2, 2] = c, s, 1.0, -s, c
    xf = np.zeros((n, 4, 4), dtype=TRANSFORM_DTYPE)
    xf[:, :3, :3] = rot * scale[:, None, :]
    xf[:, :3, 3] = pos
    xf[:, 3, 3] = 1.0
    return xf


def yawed(rng: np.random.Generator, pos: np.ndarray, scale: tuple[float, float]) -> np.ndarray:
    """Instances at pos (n, 3), each scaled by a factor drawn from [scale[0], scale[1]),
    then turned by a random yaw (drawn in that order) -> (n, 4, 4)."""
    n = len(pos)
    s = rng.uniform(*scale, size=n)
    return placement(rng.uniform(0, 2 * np.pi, n), np.repeat(s[:, None], 3, 1), pos)


def scatter(rng: np.random.Generator, n: int, half_extent: float, min_dist: float) -> np.ndarray:
    """n points in the square [-h, h]^2 kept min_dist apart where possible (dart throwing).

    returns : (n, 2) float64 (x, z)
    """
    pts = np.empty((0, 2))
    dist = min_dist
    while len(pts) < n:
        cand = rng.uniform(-half_extent, half_extent, size=(4 * n, 2))
        for c in cand:  # one loop per candidate point, a few hundred at most
            if len(pts) == n:
                break
            if len(pts) == 0 or np.min(np.sum((pts - c) ** 2, axis=1)) >= dist**2:
                pts = np.vstack([pts, c])
        dist *= 0.8  # too crowded: relax so the loop always ends
    return pts


def sky(strength: float = 1.0) -> Environment:
    """A blue-zenith, pale-horizon sky with radiance around 0.5-1 (moderate)."""
    return Environment(
        kind="sky",
        zenith=tuple(float(strength * x) for x in (0.25, 0.42, 0.85)),
        horizon=tuple(float(strength * x) for x in (0.85, 0.88, 0.92)),
    )


def sun_panel(centre_xz, height: float, size: float, irradiance: float) -> QuadLight:
    """A square panel facing down at `height`, bright enough to give about `irradiance`
    (W/m^2) on the ground straight below it."""
    cx, cz = centre_xz
    radiance = irradiance * height**2 / size**2  # E ~ L A / d^2 for a small panel
    warm = np.array([1.0, 0.93, 0.8])
    return QuadLight(
        corner=(cx - size / 2, height, cz - size / 2),
        edge_u=(size, 0.0, 0.0),
        edge_v=(0.0, 0.0, size),  # cross(u, v) = -y: emits downwards
        radiance=tuple(float(x) for x in radiance * warm),
    )
