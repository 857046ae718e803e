"""Jitted pixel-to-pass lookups of a wavefront step: which of the step's passes a ray
belongs to (its pixel names its tile; at most one pass per tile is live) and its pixel's
index within that pass's tile, in one pass over the rows instead of a chain of numpy
integer divisions (`nprt.workers.passes.tile_of`, `Pass.local_index`)."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT)
def pass_slots(pixel, width, tile_size, slot_of_tile):
    """pixel (n,) uint32 linear y * width + x -> (n,) int64 slot_of_tile[tile] of its
    row-major tile of edge tile_size; slot_of_tile (tiles,) int64."""
    w, ts = np.uint32(width), np.uint32(tile_size)  # 32-bit divisions: twice as fast
    tiles_x = (w + ts - np.uint32(1)) // ts
    out = np.empty(pixel.shape[0], np.int64)
    for i in range(pixel.shape[0]):
        p = pixel[i]
        y = p // w
        out[i] = slot_of_tile[(y // ts) * tiles_x + (p - y * w) // ts]
    return out


@njit(**JIT)
def tile_index(pixel, width, tile_size):
    """pixel (n,) uint32 -> (n,) int64 row-major index within its tile (tiles on the right
    edge are narrower: width - x0 columns), as `Pass.local_index` of the tile's pass."""
    w, ts = np.uint32(width), np.uint32(tile_size)
    out = np.empty(pixel.shape[0], np.int64)
    for i in range(pixel.shape[0]):
        p = pixel[i]
        y = p // w
        x = p - y * w
        x0, y0 = (x // ts) * ts, (y // ts) * ts
        out[i] = np.int64(y - y0) * np.int64(min(ts, w - x0)) + np.int64(x - x0)
    return out
