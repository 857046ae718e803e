"""Neural-proxy intersection of rays with instance boxes this shard does not hold
(paper section 5): box entry point in local space, the visibility and depth nets, and
the external / internal cases of section 5.2."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from nprt.workers.kernels.sampling import normalize
from nprt.workers.wavefront.world import ShardWorld


@dataclass(frozen=True)
class Prediction:
    """Per ray: t (n,) float32 closest confident predicted hit (inf if none), inst (n,)
    int32 (-1), uncertain (n,) bool (the ray enters a box whose visibility is within the
    band, or that has no proxy, before its closest confident hit), internal (n,) bool (the
    predicted hit is a proxy's answer for a box the ray starts inside: the paper's internal
    case, whose t is the surface nearest the box exit, not the first one from the origin),
    ambiguous (n,) bool (a ray also confidently hits a box it starts inside, other than the
    chosen one: its first surface there may come before the chosen hit), first_open (n,)
    int32 (of the boxes that make a ray uncertain, the one it enters first; -1: none, or
    uncertain only for ambiguity; visiting its owner settles it exactly). A prediction
    inside the band, or an internal one within INTERNAL_MARGIN of the origin, is never a
    hit."""

    t: np.ndarray
    inst: np.ndarray
    uncertain: np.ndarray
    internal: np.ndarray
    ambiguous: np.ndarray
    first_open: np.ndarray


# The internal case's ambiguity (Prediction.ambiguous) goes to exact forwarding unless
# NPRT_PROXY_INTERNAL_AMBIGUOUS=trust (read at import: for benchmarking the rule only).
EXACT_IF_AMBIGUOUS = os.environ.get("NPRT_PROXY_INTERNAL_AMBIGUOUS", "exact") != "trust"
# Internal case, secondary rays: the depth net cannot tell on which side of the origin a
# surface lies when it is predicted within this fraction of the proxy's held-out
# 90th-percentile depth error of it; such an answer is unsure, like one in the band
# (bench/README.md, "The unsure zone around the origin"). NPRT_PROXY_INTERNAL_MARGIN
# overrides it, read at import: for benchmarking only.
INTERNAL_MARGIN = float(os.environ.get("NPRT_PROXY_INTERNAL_MARGIN", "0.5"))


def predict(world: ShardWorld, proxies: dict, remote: np.ndarray, origin: np.ndarray,
            direction: np.ndarray, tmax: np.ndarray, threshold: float | None,
            band: float, known=None, visited: np.ndarray | None = None,
            internal_margin: float = 0.0) -> Prediction:
    """origin, direction (n, 3) float32 world; tmax (n,) float32; remote (m,) int32: the
    instances to ask proxies about; threshold None: each proxy's own (calibrated at
    training); known: LocalGeometry of other remote instances, intersected exactly;
    visited: (n,) uint64 shard bitmask of each ray, whose shards' boxes are not asked about
    (their geometry was intersected exactly, and the ray carries what it found);
    internal_margin: a confident internal answer whose surface lies within this fraction
    of the proxy's held-out p90 depth error of the origin is unsure (INTERNAL_MARGIN for
    secondary rays; 0 keeps the paper's rule)."""
    n = len(origin)
    best_t = np.full(n, np.inf, np.float32)
    best_i = np.full(n, -1, np.int32)
    uncertain = np.zeros(n, bool)
    internal = np.zeros(n, bool)
    ambiguous = np.zeros(n, bool)
    first_open = np.full(n, -1, np.int32)
    if known is not None and len(known.instances) and n:
        t, inst, _, _, _ = known.intersect_closest(origin, direction, tmax)
        hit = inst >= 0
        best_t[hit], best_i[hit] = t[hit], inst[hit]
    table = world.table
    ray, inst, _, _ = table.box_entries(origin, direction, tmax, remote)
    if visited is not None and len(ray):
        owner = world.owner[inst].astype(np.uint64)  # remote instances have one owner
        keep = (visited[ray] >> owner) & np.uint64(1) == 0
        ray, inst = ray[keep], inst[keep]
    if len(ray) == 0:
        return Prediction(best_t, best_i, uncertain, internal, ambiguous, first_open)
    # Box geometry for every (ray, instance) pair at once; only the nets run per mesh.
    q = _box_queries(table, inst, origin[ray], direction[ray], tmax[ray])
    mesh = table.mesh[inst]
    vis = np.zeros(len(ray), np.float32)
    t_proxy = np.full(len(ray), np.inf)
    thr = np.zeros(len(ray), np.float32)
    margin = np.zeros(len(ray))  # world-t half-width of the internal case's unsure zone
    for m in np.unique(mesh[q.crosses]):
        rows = np.flatnonzero(q.crosses & (mesh == m))
        proxy = proxies.get(int(m))
        if proxy is None:  # no proxy for this mesh: only exact forwarding can tell
            continue
        thr[rows] = proxy.meta["threshold"] if threshold is None else threshold
        v, tp = proxy.query(q.point[rows], q.qdir[rows], min_visibility=float(thr[rows[0]]))
        vis[rows], t_proxy[rows] = v, tp / q.length[rows]
        p90 = proxy.meta.get("report", {}).get("depth_err_rel_p90", 0.0)
        margin[rows] = internal_margin * p90 * float(proxy.diag) / q.length[rows]
    has_proxy = q.crosses & np.isin(mesh, np.fromiter(proxies, np.int64, len(proxies)))
    near_origin = q.internal & (vis >= thr) & (np.abs(t_proxy - q.t_box) < margin)
    unsure = has_proxy & ((np.abs(vis - thr) < band) | near_origin)
    hit = has_proxy & ~unsure & (vis >= thr)
    hit &= ~q.internal | (t_proxy <= q.t_box)  # internal: the surface lies behind the origin
    t = np.where(q.internal, q.t_box - t_proxy, q.t_box + t_proxy).astype(np.float32)
    hit &= t < tmax[ray]
    r, t, i, inner = ray[hit], t[hit], inst[hit], q.internal[hit]
    inner_hits = np.bincount(r[inner], minlength=n)  # confident internal hits per ray
    # Closest per ray; ties go to the lowest instance.
    order = np.lexsort((i, t, r))
    r, t, i, inner = r[order], t[order], i[order], inner[order]
    first = np.ones(len(r), bool)
    first[1:] = r[1:] != r[:-1]
    r, t, i, inner = r[first], t[first], i[first], inner[first]
    better = t < best_t[r]
    best_t[r[better]], best_i[r[better]] = t[better], i[better]
    internal[r[better]] = inner[better]
    # A box no proxy answers with confidence (in the band, or without a proxy) matters only
    # if the ray enters it before its closest confident hit: only then can it hide a nearer
    # surface. (Shadow rays use `uncertain` only where nothing occludes: best_t is inf.)
    t_enter = np.where(q.internal, 0.0, q.t_box)
    open_ = (unsure | (q.crosses & ~has_proxy)) & (t_enter < best_t[ray])
    uncertain[ray[open_]] = True
    o = np.flatnonzero(open_)
    o = o[np.lexsort((inst[o], t_enter[o], ray[o]))]  # per ray, nearest entry first
    lead = np.ones(len(o), bool)
    lead[1:] = ray[o[1:]] != ray[o[:-1]]
    first_open[ray[o[lead]]] = inst[o[lead]]
    # An internal t is the surface nearest the box exit; the ray's first surface in that box
    # lies anywhere in (0, t]. Any internal hit that did not win may hide a nearer surface.
    ambiguous = inner_hits - internal > 0
    if EXACT_IF_AMBIGUOUS:
        uncertain |= ambiguous
    return Prediction(best_t, best_i, uncertain, internal, ambiguous, first_open)


@dataclass(frozen=True)
class _BoxQueries:
    """Per (ray, instance) pair: crosses (p,) bool (the ray meets the local mesh box before
    tmax); internal (p,) bool (origin inside it); t_box (p,) float64 world-t of the query
    point; point, qdir (p, 3) float32 local query point and unit direction; length (p,)
    float64 local units per unit of world t."""

    crosses: np.ndarray
    internal: np.ndarray
    t_box: np.ndarray
    point: np.ndarray
    qdir: np.ndarray
    length: np.ndarray


def _box_queries(table, inst, origin, direction, tmax) -> _BoxQueries:
    """inst (p,) int32; origin, direction (p, 3) float32 world; tmax (p,) float32."""
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
    internal = t_enter <= 0.0
    # External rays query at the entry point; internal ones at the exit, reversed.
    t_box = np.where(internal, t_exit, t_enter)
    unit = normalize(d)
    point = (o + t_box[:, None] * d).astype(np.float32)
    qdir = np.where(internal[:, None], -unit, unit).astype(np.float32)
    return _BoxQueries(crosses, internal, t_box, point, qdir, np.linalg.norm(d, axis=1))
