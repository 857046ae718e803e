"""Jitted kernels over (ray, instance) crossings: rays moved into an instance's local space,
crossings grouped by base mesh for one Embree call each, taken in rounds nearest box
first, and the fold of a mesh's hits into each ray's closest so far (the tie rule)."""

from __future__ import annotations

import numpy as np
from numba import njit

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(inline="always", **JIT)
def _to_local_row(world_to_local, i, origin, direction, r, lo, ld, y):
    """lo[y], ld[y] = ray r moved by instance i's world_to_local (3, 4), in float64 then
    float32. Each row sums in the one fixed order of `nprt.workers.kernels.shade._dot`,
    (m0 x0 + m2 x2) + m1 x1, then adds the translation."""
    for a in range(3):
        m0, m1, m2 = world_to_local[i, a, 0], world_to_local[i, a, 1], world_to_local[i, a, 2]
        o = (m0 * origin[r, 0] + m2 * origin[r, 2]) + m1 * origin[r, 1]
        d = (m0 * direction[r, 0] + m2 * direction[r, 2]) + m1 * direction[r, 1]
        lo[y, a] = np.float32(o + world_to_local[i, a, 3])
        ld[y, a] = np.float32(d)


@njit(**JIT)
def to_local(inst, world_to_local, origin, direction):
    """Ray x moved by instance inst[x]: inst (n,) int32, world_to_local (m, 3, 4) float64,
    origin, direction (n, 3) float64; returns origin, direction (n, 3) float32."""
    n = inst.shape[0]
    lo, ld = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    for x in range(n):
        _to_local_row(world_to_local, inst[x], origin, direction, x, lo, ld, x)
    return lo, ld


@njit(**JIT)
def pairs_by_mesh(ray, inst, mesh_of, n_mesh, world_to_local, origin, direction):
    """(ray, instance) crossings grouped by base mesh (stable: within a mesh, the order of
    the crossings), with each ray moved into its instance's local space (as `to_local`).

    ray (p,) int64, inst (p,) int32; mesh_of (m,) int32; world_to_local (m, 3, 4) float64;
    origin, direction (n, 3) float64
    returns ray (p,) int64, inst (p,) int32, start (n_mesh + 1,) int64 (mesh g's rows are
    start[g]:start[g + 1]), local origin, direction (p, 3) float32
    """
    keep = np.ones(ray.shape[0], np.bool_)
    return _grouped(ray, inst, keep, mesh_of, n_mesh, world_to_local, origin, direction)


@njit(inline="always", **JIT)
def _grouped(ray, inst, keep, mesh_of, n_mesh, world_to_local, origin, direction):
    """`pairs_by_mesh` of the crossings where keep (p,) bool."""
    start = np.zeros(n_mesh + 1, np.int64)
    for x in range(ray.shape[0]):
        if keep[x]:
            start[mesh_of[inst[x]] + 1] += 1
    for g in range(n_mesh):
        start[g + 1] += start[g]
    q = start[n_mesh]
    fill = start[:-1].copy()
    r_out, i_out = np.empty(q, np.int64), np.empty(q, np.int32)
    lo, ld = np.empty((q, 3), np.float32), np.empty((q, 3), np.float32)
    for x in range(ray.shape[0]):
        if not keep[x]:
            continue
        r, i = ray[x], inst[x]
        y = fill[mesh_of[i]]
        fill[mesh_of[i]] += 1
        r_out[y], i_out[y] = r, i
        _to_local_row(world_to_local, i, origin, direction, r, lo, ld, y)
    return r_out, i_out, start, lo, ld


@njit(**JIT)
def entry_rank(ray, t_enter):
    """(p,) int32 position of each crossing among its ray's, nearest box entry first (ties
    in the order given). ray (p,) int64 ray-major (a ray's crossings are contiguous),
    t_enter (p,) float64."""
    p = ray.shape[0]
    rank = np.empty(p, np.int32)
    a = 0
    while a < p:
        b = a + 1
        while b < p and ray[b] == ray[a]:
            b += 1
        for x in range(a, b):
            k = 0
            for y in range(a, b):
                if t_enter[y] < t_enter[x] or (t_enter[y] == t_enter[x] and y < x):
                    k += 1
            rank[x] = k
        a = b
    return rank


@njit(**JIT)
def closest_round(ray, inst, rank, t_enter, k_lo, k_hi, cut, box_slack, mesh_of, n_mesh,
                  world_to_local, origin, direction):
    """The crossings of one round of closest-hit queries: rank in [k_lo, k_hi) and box
    entry within the ray's cut (its closest hit so far, or tmax) stretched by box_slack
    (a hit in a box entered beyond that lies beyond the cut), grouped by mesh and moved to
    local space; returns as `pairs_by_mesh`.

    rank (p,) int32 from `entry_rank`; t_enter (p,) float64; cut (n,) float32
    """
    keep = np.empty(ray.shape[0], np.bool_)
    for x in range(ray.shape[0]):
        c = np.float64(cut[ray[x]])
        keep[x] = rank[x] >= k_lo and rank[x] < k_hi and t_enter[x] <= c * (1.0 + box_slack)
    return _grouped(ray, inst, keep, mesh_of, n_mesh, world_to_local, origin, direction)


@njit(**JIT)
def fold_closest(ray, inst, t, prim, u, v, tmax, best_t, best_inst, best_prim, best_u,
                 best_v, cut):
    """Fold one mesh's Embree answers into each ray's running closest hit, in place: a hit
    (prim >= 0) at t <= tmax[ray] wins on a smaller t, and on equal t the lower instance
    (so any shard split agrees); cut[ray] follows best_t.

    ray (h,) int64; inst, prim (h,) int32; t, u, v (h,) float32; tmax (n,) float32;
    best_* (n,) running per-ray state (best_inst -1: no hit yet); cut (n,) float32
    """
    for x in range(ray.shape[0]):
        r = ray[x]
        if prim[x] < 0 or not t[x] <= tmax[r]:
            continue
        if best_inst[r] < 0 or t[x] < best_t[r] or (t[x] == best_t[r] and inst[x] < best_inst[r]):
            best_t[r], best_inst[r], best_prim[r] = t[x], inst[x], prim[x]
            best_u[r], best_v[r] = u[x], v[x]
            if t[x] < cut[r]:
                cut[r] = t[x]


@njit(**JIT)
def occluded_round(ray, inst, rank, k_lo, k_hi, occluded, mesh_of, n_mesh, world_to_local,
                   origin, direction):
    """The crossings of one round of occlusion queries: rank in [k_lo, k_hi), rays not yet
    occluded; grouped and moved as `pairs_by_mesh`."""
    keep = np.empty(ray.shape[0], np.bool_)
    for x in range(ray.shape[0]):
        keep[x] = rank[x] >= k_lo and rank[x] < k_hi and not occluded[ray[x]]
    return _grouped(ray, inst, keep, mesh_of, n_mesh, world_to_local, origin, direction)
