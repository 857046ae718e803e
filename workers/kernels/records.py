"""Hit records in compiled code: the one order of hits (`nprt.workers.wavefront.batch.precedes`,
whose constants live here) and the folds of the closest-hit stage, one loop over the rays
instead of a chain of numpy where/astype calls (most of a small batch's cost)."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

# Hit record sentinels in `hit_inst` (int32): no hit yet, or a quad light (-2 - light index).
NO_HIT = -1
LIGHT_BASE = -2
# Tie ranks (int64) of hit_inst values: quad lights first, in light order, then instances
# in instance order; "no hit" last, so any hit at or before tmax replaces it.
RANK_LIGHT0 = -(1 << 40)
RANK_NO_HIT = 1 << 40


@njit(inline="always", **JIT)
def rank1(h):
    """`batch.tie_rank` of one hit_inst."""
    h = np.int64(h)
    if h >= 0:
        return h
    if h == NO_HIT:
        return np.int64(RANK_NO_HIT)
    return np.int64(RANK_LIGHT0 + LIGHT_BASE) - h


@njit(inline="always", **JIT)
def precedes1(t_a, inst_a, prim_a, t_b, inst_b, prim_b):
    """`batch.precedes` of one pair of records (t float32)."""
    t_a, t_b = np.float32(t_a), np.float32(t_b)
    if t_a < t_b:
        return True
    if not t_a == t_b:
        return False
    r_a, r_b = rank1(inst_a), rank1(inst_b)
    return r_a < r_b or (r_a == r_b and prim_a < prim_b)


@njit(**JIT)
def local_winners(run_t, run_inst, run_prim, run_u, run_v, tmax, rec_inst, rec_prim,
                  use_record):
    """The local hits run_* (n,) (run_inst -1: none) that beat the record a ray carries:
    with use_record, those that precede (tmax, rec_inst, rec_prim); else those before
    tmax. Returns t (tmax where none), inst (-1), prim (-1), u, v (0) as (n,) float32 /
    int32."""
    n = run_t.shape[0]
    t, inst = tmax.copy(), np.full(n, -1, np.int32)
    prim = np.full(n, -1, np.int32)
    u, v = np.zeros(n, np.float32), np.zeros(n, np.float32)
    for r in range(n):
        if run_inst[r] < 0:
            continue
        if use_record:
            better = precedes1(run_t[r], run_inst[r], run_prim[r], tmax[r], rec_inst[r],
                               rec_prim[r])
        else:
            better = run_t[r] < tmax[r]
        if better:
            t[r], inst[r], prim[r], u[r], v[r] = (run_t[r], run_inst[r], run_prim[r], run_u[r],
                                                 run_v[r])
    return t, inst, prim, u, v


@njit(**JIT)
def with_lights(t, inst, prim, u, v, rec_inst, rec_prim, rec_u, rec_v, light_t, light):
    """The new record of each ray: the local winner (inst >= 0, from `local_winners`) or
    the record it carried, then a quad light hit (light >= 0 at light_t) if it precedes
    that. Returns tmax (n,) float32, hit_inst, hit_prim (n,) int32, hit_u, hit_v (n,)
    float32."""
    n = t.shape[0]
    o_t, o_inst = np.empty(n, np.float32), np.empty(n, np.int32)
    o_prim = np.empty(n, np.int32)
    o_u, o_v = np.empty(n, np.float32), np.empty(n, np.float32)
    for r in range(n):
        got = inst[r] >= 0
        h_inst = inst[r] if got else rec_inst[r]
        h_prim = prim[r] if got else rec_prim[r]
        lit = light[r] >= 0 and precedes1(light_t[r], LIGHT_BASE - light[r], -1, t[r], h_inst,
                                          h_prim)
        if lit:
            o_t[r], o_inst[r], o_prim[r] = light_t[r], LIGHT_BASE - light[r], -1
            o_u[r], o_v[r] = 0.0, 0.0
        else:
            o_t[r], o_inst[r], o_prim[r] = t[r], h_inst, h_prim
            o_u[r], o_v[r] = (u[r], v[r]) if got else (rec_u[r], rec_v[r])
    return o_t, o_inst, o_prim, o_u, o_v
