"""The shard side of nprt.workers.filmsum: contributions rounded to the fixed quantum and
added as two-word integers, one pass over them (no sort, no per-channel bincounts)."""

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
        p = idx[i]
        for c in range(3):
            v = rgb[i, c]
            if not (abs(v) < _LIMIT):  # also catches NaN
                if not outside[i]:
                    outside[i] = True
                    flagged += 1
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
