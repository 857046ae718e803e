"""Jitted kernels over (ray, instance) pairs: rays moved into an instance's local space
(float64, then float32), the one way every traversal kernel does it."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(inline="always", **JIT)
def _to_local_row(world_to_local, i, origin, direction, r, lo, ld, y):
    """lo[y], ld[y] = ray r moved by instance i's world_to_local (3, 4), in float64 then
    float32. Each row sums in the one fixed order of `nprt.workers.kernels.shade._dot`,
    (m0 x0 + m2 x2) + m1 x1, then adds the translation."""
    for a in range(3):
        m0, m1, m2 = world_to_local[i, a, 0], world_to_local[i, a, 1], world_to_local[i, a, 2]
        o = (m0 * origin[r, 0] + m2 * origin[r, 2]) + m1 * origin[r, 1]
        d = (m0 * direction[r, 0] + m2 * direction[r, 2]) + m1 * direction[r, 1]
        lo[y, a] = np.float32(o + world_to_local[i, a, 3])
        ld[y, a] = np.float32(d)


@njit(**JIT)
def to_local(inst, world_to_local, origin, direction):
    """Ray x moved by instance inst[x]: inst (n,) int32, world_to_local (m, 3, 4) float64,
    origin, direction (n, 3) float64; returns origin, direction (n, 3) float32."""
    n = inst.shape[0]
    lo, ld = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    for x in range(n):
        _to_local_row(world_to_local, inst[x], origin, direction, x, lo, ld, x)
    return lo, ld
