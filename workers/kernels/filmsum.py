"""The shard side of nprt.workers.filmsum: contributions rounded to the fixed quantum and
added as two-word integers, one pass over them (no sort, no per-channel bincounts), as
they are made (`splat`)."""

from __future__ import annotations

import numpy as np
from numba import njit

from nprt.workers.filmsum import LSB_EXP, MAX_EXP, WORD_BITS

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
_SCALE = 2.0 ** -LSB_EXP
_WORD = 2.0 ** WORD_BITS
_INV_WORD = 2.0 ** -WORD_BITS
_LIMIT = 2.0 ** MAX_EXP
_LO_END = np.int64(1) << np.int64(WORD_BITS)


@njit(**JIT)
def accumulate(idx, rgb, words, outside):
    """Add rgb (m, 3) float64 at pixels idx (m,) int64 into words (n, 3, 2) int64.

    Values the words cannot hold (not finite, or |v| >= 2^MAX_EXP) are left out and flagged
    in outside (m,) bool; returns how many rows have one."""
    flagged = 0
    w4 = words.reshape((1, words.shape[0], 3, 2))
    for i in range(idx.shape[0]):
        flagged += _add(w4, 0, idx[i], rgb, i, outside)
    return flagged


@njit(**JIT)
def splat(pixel, rgb, width, tile_size, slot_of_tile, x0, y0, tile_w, words, outside):
    """`accumulate` of a step's contributions, each at its pixel's index in the tile of its
    pass: pixel (m,) uint32 linear y * width + x; rgb (m, 3) float32 or float64;
    slot_of_tile (tiles,) int64 the pass of each row-major tile of edge tile_size (-1:
    none; such rows are dropped); x0, y0, tile_w (t,) int64 each pass's tile origin and
    width; words (t, n, 3, 2) int64 the passes' films; outside (m,) bool as
    `accumulate`'s. Returns how many rows were flagged."""
    w, ts = np.uint32(width), np.uint32(tile_size)  # 32-bit divisions: twice as fast
    tiles_x = (w + ts - np.uint32(1)) // ts
    flagged = 0
    for i in range(pixel.shape[0]):
        p = pixel[i]
        y = p // w
        x = p - y * w
        j = slot_of_tile[(y // ts) * tiles_x + x // ts]
        if j < 0:
            continue
        idx = (np.int64(y) - y0[j]) * tile_w[j] + (np.int64(x) - x0[j])
        flagged += _add(words, j, idx, rgb, i, outside)
    return flagged


@njit(inline="always", **JIT)
def _add(words, j, p, rgb, i, outside):
    """Add row i of rgb at pixel p of film j of words (t, n, 3, 2); returns 1 if the row
    was flagged here, else 0."""
    flagged = 0
    for c in range(3):
        v = np.float64(rgb[i, c])
        if not (abs(v) < _LIMIT):  # also catches NaN
            if not outside[i]:
                outside[i] = True
                flagged = 1
            continue
        q = np.rint(v * _SCALE)  # exact scaling; one rounding to the quantum
        hi = np.floor(q * _INV_WORD)
        lo = np.int64(q - hi * _WORD)  # exact: q's low bits, in [0, 2^60)
        words[j, p, c, 0] += np.int64(hi)
        s = words[j, p, c, 1] + lo
        if s >= _LO_END:
            s -= _LO_END
            words[j, p, c, 0] += 1
        words[j, p, c, 1] = s
    return flagged
