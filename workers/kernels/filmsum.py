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
    for i in range(idx.shape[0]):
        flagged += _add(words, idx[i], rgb, i, outside)
    return flagged


@njit(**JIT)
def splat(pixel, rgb, tok, slot, width, x0, y0, tile_w, words, outside):
    """`accumulate` of the rows of one pass, indexed by their pixel within its tile: the
    rows i with tok[i] == slot (every row where tok is empty). pixel (m,) uint32 linear
    y * width + x; rgb (m, 3) float32 or float64; tok (m,) or (0,) int64; the pass's tile
    starts at column x0, row y0 and is tile_w pixels wide; words (n, 3, 2) int64 its
    film; outside (m,) bool as `accumulate`'s. Returns how many rows were flagged."""
    w = np.uint32(width)
    every = tok.shape[0] == 0
    flagged = 0
    for i in range(pixel.shape[0]):
        if not every and tok[i] != slot:
            continue
        p = pixel[i]
        y = p // w  # 32-bit divisions: twice as fast
        idx = (np.int64(y) - y0) * tile_w + (np.int64(p - y * w) - x0)
        flagged += _add(words, idx, rgb, i, outside)
    return flagged


@njit(inline="always", **JIT)
def _add(words, p, rgb, i, outside):
    """Add row i of rgb at pixel p; returns 1 if the row was flagged here, else 0."""
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
        words[p, c, 0] += np.int64(hi)
        s = words[p, c, 1] + lo
        if s >= _LO_END:
            s -= _LO_END
            words[p, c, 0] += 1
        words[p, c, 1] = s
    return flagged
