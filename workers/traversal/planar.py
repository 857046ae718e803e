"""Meshes that lie in one plane of their local axes (a ground quad), where the walks may
skip Embree for a ray that leaves the plane: Embree's robust triangle test then rejects
every triangle, so skipping it changes no answer (`nprt.workers.kernels.crossings.
_leaves_plane`, which checks a ray against the row `plane_row` makes).

Why no hit is possible: in robust mode Embree tests a triangle with its Pluecker
intersector, on the vertices minus the ray's origin in float32. When every vertex has
the same coordinate c on axis a, those differences agree on axis a bit for bit, so the
edges have a zero there, the other two components of the normal Ng are products with a
zero (+-0 exactly), and den = 2 Ng_a D_a, T = 2 (c - O_a) Ng_a each carry one rounded
product. Its depth test compares t = T / den (as rcp(den) * T, or as T ^ sign(den)
against |den| tnear) with tnear = 0: when c - O_a and D_a have opposite signs (the ray
moves away from the plane) and nothing underflows, t < 0 and the triangle is rejected.
The row's bounds keep every quantity normal: |c - O_a| >= GAP_MIN, DIR_MIN <= |D_a|
<= DIR_MAX, and the origin within `reach` of the mesh, near enough that Embree's
rounded |Ng_a| stays at least half the smallest triangle's (twice) area."""

from __future__ import annotations

import numpy as np

# A local origin at least this far off the plane, and a direction component in
# [DIR_MIN, DIR_MAX] on its axis: T, den and T / den then stay far from float32 underflow
# and overflow (see the module docstring).
GAP_MIN = 1e-20
DIR_MIN = 1e-10
DIR_MAX = 1e10
# Meshes larger than this (local units) are not marked: the bounds below assume no
# product of coordinates overflows float32.
EXTENT_MAX = 1e6
# The smallest twice-area a planar mesh's triangles may have (smaller ones: not marked).
AREA2_MIN = 1e-12
_U = 2.0**-24  # float32 unit roundoff


def plane_row(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float, float]:
    """(axis, c, reach) for one mesh: vertices (v, 3) float32-representable, faces (f, 3)
    int. axis 0, 1 or 2 when every vertex a face uses has coordinate c there (float32,
    exactly), else -1 (then c and reach are 0). reach: the largest |coordinate| of a local
    origin (each axis) for which `_leaves_plane` may skip the mesh."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"plane_row: vertices (v, 3) and faces (f, 3), got {v.shape} and "
                         f"{f.shape}")
    none = (-1.0, 0.0, 0.0)
    if len(f) == 0 or not np.isfinite(v).all():
        return none
    tri = v[f].astype(np.float64)  # (f, 3, 3) exact float32 values
    extent = float(np.abs(tri).max())
    if extent > EXTENT_MAX:
        return none
    for a in range(3):
        c = tri[0, 0, a]
        if not (tri[:, :, a] == c).all():
            continue
        p, q = [x for x in range(3) if x != a]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]  # (f, 3), exact
        area2 = np.abs(e1[:, q] * e2[:, p] - e1[:, p] * e2[:, q])  # (f,) |Ng_a| unrounded
        edge = max(float(np.abs(e1).max()), float(np.abs(e2).max()),
                   float(np.abs(tri[:, 2] - tri[:, 1]).max()))
        reach = 2.0 * extent + 1.0
        # Embree's vertices minus the origin are each off by <= U R, its edges by
        # <= delta, so its rounded Ng_a is off by <= eps from the true twice-area.
        r = extent + reach
        delta = 5.0 * _U * r + 1e-30
        eps = 4.0 * edge * delta + 2.0 * delta**2 + 4.0 * _U * (edge + delta) ** 2
        smallest = float(area2.min())
        if smallest < AREA2_MIN or eps > smallest / 2.0:
            return none
        return float(a), float(np.float32(c)), reach
    return none


def plane_rows(meshes: dict[int, np.ndarray | tuple], n: int) -> np.ndarray:
    """planes (n, 3) float64 for mesh indices 0 .. n - 1: `plane_row` of each (vertices,
    faces) in meshes {index: (vertices, faces)}, (-1, 0, 0) for the others."""
    rows = np.zeros((n, 3))
    rows[:, 0] = -1.0
    for m, (vertices, faces) in meshes.items():
        rows[m] = plane_row(vertices, faces)
    return rows
