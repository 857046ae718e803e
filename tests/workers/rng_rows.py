"""Compiled row loops over nprt.workers.kernels.rng's inlined hash, for the tests that check
it (against the numpy copy in oracles.py) and that draw the shading kernels' numbers."""

from __future__ import annotations

import numpy as np
from numba import njit

from nprt.workers.kernels.rng import JIT, dim_key, uniform_keyed


@njit(**JIT)
def uniform_rows(seed, rows, pixel, sample, bounce, dim):
    """(k,) float64 uniforms of one dimension for `rows` (k,) int64 of pixel, sample (n,)
    u32 and bounce (n,) u8."""
    key = dim_key(np.uint64(seed), np.uint64(dim))
    out = np.empty(len(rows))
    for j in range(len(rows)):
        i = rows[j]
        out[j] = uniform_keyed(key, pixel[i], sample[i], bounce[i])
    return out


@njit(**JIT)
def _uniform(seed, pixel, sample, bounce, dim):
    out = np.empty(len(pixel))
    for i in range(len(pixel)):
        out[i] = uniform_keyed(dim_key(seed, dim[i]), pixel[i], sample[i], bounce[i])
    return out


def uniform(seed: int, pixel: np.ndarray, sample: np.ndarray, bounce, dim) -> np.ndarray:
    """Uniform numbers in [0, 1).

    pixel  : (n,) uint32
    sample : (n,) uint32
    bounce : int or (n,) uint8
    dim    : int or (n,) int
    returns (n,) float64
    """
    n = len(pixel)
    return _uniform(np.uint64(seed & 0xFFFFFFFFFFFFFFFF),
                    np.ascontiguousarray(pixel, np.uint32), np.ascontiguousarray(sample, np.uint32),
                    np.ascontiguousarray(np.broadcast_to(bounce, (n,)), np.uint64),
                    np.ascontiguousarray(np.broadcast_to(dim, (n,)), np.uint64))
