"""numba kernels: the top-level BVH, shading, the counter-based RNG, sampling, origin offsets."""

import numpy as np


def owned(a, dtype=None) -> np.ndarray:
    """a as a writable C-contiguous array (of dtype), copied only where it is not one: a
    column read back from Ray's object store is read-only, and numba compiles a kernel
    again for read-only arrays."""
    out = np.ascontiguousarray(a, dtype)
    return out if out.flags.writeable else out.copy()
