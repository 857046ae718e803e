"""Self-intersection-free ray origins: the integer-ULP offset along the geometric
normal from Ray Tracing Gems, ch. 6 ("A Fast and Robust Method for Avoiding
Self-Intersection"). embreex fixes tnear at 0, so every spawned ray goes through here."""

from __future__ import annotations

import numpy as np

_ORIGIN = np.float32(1.0 / 32.0)
_FLOAT_SCALE = np.float32(1.0 / 65536.0)
_INT_SCALE = np.float32(256.0)


def offset_ray_origin(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Push points off their surface to the side that `n` points to.

    p : (n, 3) float32 world hit points (computed from barycentrics)
    n : (n, 3) float32 geometric normals oriented toward the outgoing side
    returns (n, 3) float32
    """
    p = np.ascontiguousarray(p, dtype=np.float32)
    n = np.asarray(n, dtype=np.float32)
    of_i = (_INT_SCALE * n).astype(np.int32)
    p_i = p.view(np.int32) + np.where(p < 0, -of_i, of_i)
    p_far = p_i.view(np.float32)
    return np.where(np.abs(p) < _ORIGIN, p + _FLOAT_SCALE * n, p_far).astype(np.float32)
