"""A wavefront step's statistics counted in place: one pass over a batch's rows adds each to
its (pass, kind) or (pass, hops) cell, where a bincount of pass * width + key made four
temporaries and a (t * width) histogram per call (a step counts a dozen times)."""

from __future__ import annotations

from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT)
def add_pairs(out, tok, key, cap, mask):
    """out (t, w) int64 += 1 at [tok[i], min(key[i], cap)] for each row i where mask[i] (or
    every row, when mask has no rows). tok (n,) int64 in [0, t), key (n,) uint8 or int64,
    mask (n,) or (0,) bool."""
    t = out.shape[0]
    every = mask.shape[0] == 0
    for i in range(tok.shape[0]):
        if every or mask[i]:
            j = tok[i]
            if j < 0 or j >= t:
                raise ValueError("add_pairs: a row's pass is not in this step")
            k = key[i]
            out[j, min(k, cap)] += 1


@njit(**JIT)
def add_column(out, tok, col):
    """out (t, w) int64 += 1 at [tok[i], col] for each row i; tok (n,) int64 in [0, t)."""
    t = out.shape[0]
    for i in range(tok.shape[0]):
        j = tok[i]
        if j < 0 or j >= t:
            raise ValueError("add_column: a row's pass is not in this step")
        out[j, col] += 1
