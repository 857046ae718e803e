"""A ray moved into an instance's local space (float64, then float32), the one way every
traversal kernel does it; inlined into them (tests/workers/oracles.to_local runs it alone)."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(inline="always", **JIT)
def to_local_ray(world_to_local, i, origin, direction, r):
    """Ray r moved by instance i's world_to_local (3, 4), in float64 then float32: local
    origin and direction as six float32 scalars. Each row sums in the one fixed order of
    `nprt.workers.kernels.shade._dot`, (m0 x0 + m2 x2) + m1 x1, then adds the translation."""
    o0, o1, o2 = origin[r, 0], origin[r, 1], origin[r, 2]
    d0, d1, d2 = direction[r, 0], direction[r, 1], direction[r, 2]
    w = world_to_local
    return (np.float32(((w[i, 0, 0] * o0 + w[i, 0, 2] * o2) + w[i, 0, 1] * o1) + w[i, 0, 3]),
            np.float32(((w[i, 1, 0] * o0 + w[i, 1, 2] * o2) + w[i, 1, 1] * o1) + w[i, 1, 3]),
            np.float32(((w[i, 2, 0] * o0 + w[i, 2, 2] * o2) + w[i, 2, 1] * o1) + w[i, 2, 3]),
            np.float32((w[i, 0, 0] * d0 + w[i, 0, 2] * d2) + w[i, 0, 1] * d1),
            np.float32((w[i, 1, 0] * d0 + w[i, 1, 2] * d2) + w[i, 1, 1] * d1),
            np.float32((w[i, 2, 0] * d0 + w[i, 2, 2] * d2) + w[i, 2, 1] * d1))
