"""Rays for training and checking a proxy: jittered points on the proxy box, stratified
inward directions, labelled (hit, t) by Embree; plus internal rays as the renderer sees them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nprt.scene.model import Mesh

SAMPLE_DTYPE = np.float32
# The proxy box is the mesh AABB grown by this fraction of its diagonal, so training rays
# start strictly outside the geometry (a box mesh's faces lie exactly on its AABB).
BOX_PAD_REL = 1e-4
# Share of rays spread evenly over faces; the rest follows face area (how often an
# isotropic ray field crosses each face), so thin faces are still learned.
FACE_UNIFORM_SHARE = 0.25
DIR_BANDS, DIR_SECTORS = 2, 4  # 8 direction regions per hemisphere


@dataclass(frozen=True)
class RaySamples:
    """Proxy queries with their Embree ground truth (local space).

    points     : (n, 3) float32, on the proxy box surface
    directions : (n, 3) float32, unit, pointing into the box
    hit        : (n,) bool, the ray hits the mesh before leaving the box
    t          : (n,) float32, distance to the first hit (inf where no hit)
    """

    points: np.ndarray
    directions: np.ndarray
    hit: np.ndarray
    t: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    @property
    def visibility(self) -> np.ndarray:
        """(n,) float32 training target of the visibility net."""
        return self.hit.astype(SAMPLE_DTYPE)


@dataclass(frozen=True)
class InternalRays:
    """Rays starting inside the box, with the reversed exit-point query the renderer makes.

    origins, directions : (n, 3) float32, the rays themselves (directions unit)
    t_bbox      : (n,) float32, distance from origin to the box exit
    query       : RaySamples for (exit point, -direction), labelled like any query
    occluded    : (n,) bool, the ray hits the mesh within (0, t_bbox)
    t_first     : (n,) float32, distance from origin to its first hit (inf where none)
    """

    origins: np.ndarray
    directions: np.ndarray
    t_bbox: np.ndarray
    query: RaySamples
    occluded: np.ndarray
    t_first: np.ndarray


def proxy_box(bounds: np.ndarray) -> np.ndarray:
    """(2, 3) float64 box the proxy is trained on: `bounds` (2, 3) padded on every side."""
    lo, hi = np.asarray(bounds, np.float64)
    diag = float(np.linalg.norm(hi - lo))
    # The absolute term keeps the pad above float32 spacing for meshes far from the origin.
    pad = BOX_PAD_REL * diag + 1e-6 * float(np.abs(bounds).max()) + 1e-12
    return np.stack([lo - pad, hi + pad])


def box_exit(box: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each ray to where it leaves `box` (2, 3); origins inside or on it.

    origins, directions : (n, 3) float64; returns (n,) float64 >= 0
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - origins) / directions
        t1 = (box[1] - origins) / directions
    # fmin/fmax drop the NaN of 0/0 (point on a slab plane, zero direction component).
    return np.maximum(np.fmin.reduce(np.fmax(t0, t1), axis=1), 0.0)


def face_counts(box: np.ndarray, n: int) -> np.ndarray:
    """(6,) int64 rays per face (face 2a is the min-face of axis a, 2a+1 the max-face)."""
    ext = box[1] - box[0]
    area = np.array([ext[(a + 1) % 3] * ext[(a + 2) % 3] for a in range(3) for _ in (0, 1)])
    w = (1 - FACE_UNIFORM_SHARE) * area / area.sum() + FACE_UNIFORM_SHARE / 6
    exact = w * n
    counts = np.floor(exact).astype(np.int64)
    rest = np.argsort(-(exact - counts), kind="stable")[: n - counts.sum()]
    counts[rest] += 1
    return counts


def _face_rays(rng, box, face: int, count: int, grid: int):
    """Stratified rays on one face: a grid x grid cell and one of 8 direction regions each."""
    axis, side = divmod(face, 2)
    ta, tb = (axis + 1) % 3, (axis + 2) % 3
    strata = grid * grid * DIR_BANDS * DIR_SECTORS
    reps = -(-count // strata)
    idx = np.concatenate([rng.permutation(strata) for _ in range(reps)])[:count]
    cell, region = np.divmod(idx, DIR_BANDS * DIR_SECTORS)
    ci, cj = np.divmod(cell, grid)
    band, sector = np.divmod(region, DIR_SECTORS)
    jit = rng.random((count, 4))
    lo, hi = box
    p = np.empty((count, 3))
    p[:, axis] = hi[axis] if side else lo[axis]
    p[:, ta] = lo[ta] + (ci + jit[:, 0]) / grid * (hi[ta] - lo[ta])
    p[:, tb] = lo[tb] + (cj + jit[:, 1]) / grid * (hi[tb] - lo[tb])
    # Cosine-weighted (Malley) within each region: the density of an isotropic ray field
    # crossing the face, which is what the renderer's box entries follow.
    u1 = (band + jit[:, 2]) / DIR_BANDS
    phi = 2 * np.pi * (sector + jit[:, 3]) / DIR_SECTORS
    sin_t, cos_t = np.sqrt(u1), np.sqrt(1 - u1)
    d = np.empty((count, 3))
    d[:, axis] = -cos_t if side else cos_t
    d[:, ta] = sin_t * np.cos(phi)
    d[:, tb] = sin_t * np.sin(phi)
    return p, d


def label(geometry, box: np.ndarray, points: np.ndarray, directions: np.ndarray) -> RaySamples:
    """Embree ground truth for queries: first hit before the ray leaves `box`.

    points, directions : (n, 3) float64 or float32; returns float32 RaySamples
    """
    p = np.asarray(points, SAMPLE_DTYPE)
    d = np.asarray(directions, SAMPLE_DTYPE)
    tmax = box_exit(box, p.astype(np.float64), d.astype(np.float64)).astype(SAMPLE_DTYPE)
    t, _, _, _ = geometry.intersect_closest(p, d, tmax)
    hit = np.isfinite(t)
    return RaySamples(p, d, hit, t.astype(SAMPLE_DTYPE))


def _geometry(mesh: Mesh, geometry):
    if geometry is not None:
        return geometry
    from nprt.workers.traversal.geometry import MeshGeometry

    return MeshGeometry(mesh)


def sample_rays(mesh: Mesh, n: int, seed: int, grid: int = 128, geometry=None) -> RaySamples:
    """n labelled queries on the proxy box of `mesh`, deterministic in `seed`.

    Each face gets a grid x grid lattice; every (cell, direction region) stratum is used once
    per pass in a seeded random order, so any n spreads evenly over the surface.
    geometry : a MeshGeometry of `mesh` to reuse (built if None)
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    rng = np.random.default_rng(seed)
    box = proxy_box(mesh.bounds)
    parts = [_face_rays(rng, box, f, int(c), grid) for f, c in enumerate(face_counts(box, n))
             if c > 0]
    p = np.concatenate([q for q, _ in parts])  # (n, 3) float64
    d = np.concatenate([q for _, q in parts])
    order = rng.permutation(n)  # interleave faces so any prefix is a fair subsample
    return label(_geometry(mesh, geometry), box, p[order], d[order])


def sample_internal_rays(mesh: Mesh, n: int, seed: int, geometry=None) -> InternalRays:
    """n rays with origins uniform in the mesh box and isotropic directions (shadow and
    secondary rays leaving a surface inside an instance box), with their proxy queries."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(mesh.bounds, np.float64)
    box = proxy_box(mesh.bounds)
    o = lo + rng.random((n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_bbox = box_exit(box, o, d)
    geo = _geometry(mesh, geometry)
    query = label(geo, box, o + t_bbox[:, None] * d, -d)
    o32, d32 = o.astype(SAMPLE_DTYPE), d.astype(SAMPLE_DTYPE)
    t_bbox32 = t_bbox.astype(SAMPLE_DTYPE)
    # embreex writes tfar into the tmax array it is given: pass a copy.
    t_first, _, _, _ = geo.intersect_closest(o32, d32, t_bbox32.copy())
    return InternalRays(o32, d32, t_bbox32, query, np.isfinite(t_first), t_first)
