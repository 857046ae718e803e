"""Neural-proxy intersection of rays with instance boxes this shard does not hold
(paper section 5): box entry point in local space, the visibility and depth nets, and
the external / internal cases of section 5.2."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.sampling import normalize
from workers.world import ShardWorld


@dataclass(frozen=True)
class Prediction:
    """Per ray: t (n,) float32 closest confident predicted hit (inf if none), inst (n,)
    int32 (-1), uncertain (n,) bool (some visibility within the band, or a box with no
    proxy). A prediction inside the band is never a hit: only exact forwarding decides it."""

    t: np.ndarray
    inst: np.ndarray
    uncertain: np.ndarray


def predict(world: ShardWorld, proxies: dict, remote: np.ndarray, origin: np.ndarray,
            direction: np.ndarray, tmax: np.ndarray, threshold: float | None,
            band: float, known=None) -> Prediction:
    """origin, direction (n, 3) float32 world; tmax (n,) float32; remote (m,) int32: the
    instances to ask proxies about; threshold None: each proxy's own (calibrated at
    training); known: LocalGeometry of other remote instances, intersected exactly."""
    n = len(origin)
    best_t = np.full(n, np.inf, np.float32)
    best_i = np.full(n, -1, np.int32)
    uncertain = np.zeros(n, bool)
    if known is not None and len(known.instances) and n:
        t, inst, _, _, _ = known.intersect_closest(origin, direction, tmax)
        hit = inst >= 0
        best_t[hit], best_i[hit] = t[hit], inst[hit]
    table = world.table
    ray, inst, _, _ = table.box_entries(origin, direction, tmax, remote)
    if len(ray) == 0:
        return Prediction(best_t, best_i, uncertain)
    mesh = table.mesh[inst]
    for m in np.unique(mesh):
        sel = mesh == m
        r, i = ray[sel], inst[sel]
        proxy = proxies.get(int(m))
        if proxy is None:  # no proxy for this mesh: only exact forwarding can tell
            uncertain[r] = True
            continue
        thr = proxy.meta["threshold"] if threshold is None else threshold
        t_hit, vis = _query(table, proxy, i, origin[r], direction[r], tmax[r], thr)
        unsure = np.abs(vis - thr) < band if band > 0 else np.zeros(len(r), bool)
        uncertain[r[unsure]] = True
        ok = (t_hit < tmax[r]) & ~unsure
        r, t_hit, i = r[ok], t_hit[ok], i[ok]
        order = np.lexsort((i, t_hit, r))
        r, t_hit, i = r[order], t_hit[order], i[order]
        first = np.ones(len(r), bool)
        first[1:] = r[1:] != r[:-1]
        r, t_hit, i = r[first], t_hit[first], i[first]
        better = t_hit < best_t[r]
        best_t[r[better]] = t_hit[better]
        best_i[r[better]] = i[better]
    return Prediction(best_t, best_i, uncertain)


def _query(table, proxy, inst, origin, direction, tmax, threshold):
    """Predicted hit distance (p,) float32 (inf for a predicted miss) and visibility (p,)."""
    m = table.world_to_local[inst]  # (p, 3, 4) float64
    o = np.einsum("pij,pj->pi", m[:, :, :3], origin.astype(np.float64)) + m[:, :, 3]
    d = np.einsum("pij,pj->pi", m[:, :, :3], direction.astype(np.float64))
    lo, hi = table.local_bounds[inst, 0], table.local_bounds[inst, 1]  # (p, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0, t1 = (lo - o) * inv, (hi - o) * inv
        t_enter = np.fmax.reduce(np.fmin(t0, t1), axis=1)
        t_exit = np.fmin.reduce(np.fmax(t0, t1), axis=1)
    crosses = (t_exit >= np.maximum(t_enter, 0.0)) & (t_enter < tmax)
    length = np.linalg.norm(d, axis=1)  # local units per unit of t
    unit = normalize(d)
    internal = t_enter <= 0.0
    # External rays query at the entry point; internal ones at the exit, reversed.
    t_box = np.where(internal, t_exit, t_enter)
    point = o + t_box[:, None] * d
    qdir = np.where(internal[:, None], -unit, unit)
    vis = np.zeros(len(inst), np.float32)
    t_proxy = np.full(len(inst), np.inf)
    rows = np.flatnonzero(crosses)
    if len(rows):
        v, tp = proxy.query(point[rows].astype(np.float32), qdir[rows].astype(np.float32),
                            min_visibility=threshold)
        vis[rows] = v
        t_proxy[rows] = tp / length[rows]
    hit = crosses & (vis >= threshold)
    hit &= ~internal | (t_proxy <= t_box)  # internal: the surface must lie behind the origin
    t = np.where(internal, t_box - t_proxy, t_box + t_proxy)
    return np.where(hit, t, np.inf).astype(np.float32), vis
