"""Where a wavefront step's rows go, in one pass each: the rows grouped by target (those that
end here, then those for each other shard, each group in row order: a stable argsort of the
targets gives the same order in O(n log n), and the rows that end needed a scan of their
own), and the rays that leave only to be shaded by their hit's owner marked."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT)
def group_rows(target, k):
    """target (n,) int32, each -1 (ends here) or a shard in [0, k) -> (order (n,) int64,
    starts (k + 2,) int64): order[starts[0]:starts[1]] are the rows that end here and
    order[starts[t + 1]:starts[t + 2]] the rows for shard t, each group in row order."""
    n = target.shape[0]
    starts = np.zeros(k + 2, np.int64)
    for i in range(n):
        if target[i] < -1 or target[i] >= k:
            raise ValueError("group_rows: a target outside [-1, k)")
        starts[target[i] + 2] += 1
    for g in range(1, k + 2):
        starts[g] += starts[g - 1]
    at = starts[:k + 1].copy()  # next free slot of each group
    order = np.empty(n, np.int64)
    for i in range(n):
        g = target[i] + 1
        order[at[g]] = i
        at[g] += 1
    return order, starts


@njit(**JIT)
def mark_for_owner(flags, target, hit_inst, owner, bit):
    """flags (n,) uint8 -> (a copy with `bit` set on each row leaving (target (n,) int32 a
    shard) for the shard owning its hit (owner[hit_inst], owner (m,) int32; hit_inst (n,)
    int32, negative: no instance hit), whether any row was marked). One pass, where a
    numpy expression made five temporaries."""
    out = flags.copy()
    marked = False
    for i in range(flags.shape[0]):
        t, h = target[i], hit_inst[i]
        if t >= 0 and h >= 0 and owner[h] == t:
            out[i] |= bit
            marked = True
    return out, marked
