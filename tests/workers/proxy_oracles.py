"""Numpy oracle of nprt.workers.routing.proxy_query.predict: the formulas its compiled
kernels (nprt.workers.routing.proxy_pairs) replaced, kept for the tests alone. Each kernel
must give these bits. No product code imports this module."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nprt.workers.kernels.sampling import normalize
from nprt.workers.routing.exact import first_of_runs
from nprt.workers.routing.proxy_query import (
    Prediction,
    QueryKnobs,
    known_hits,
    nothing_asked,
)
from nprt.workers.wavefront.world import ShardWorld


def predict_numpy(world: ShardWorld, proxies: dict, remote: np.ndarray, origin: np.ndarray,
                  direction: np.ndarray, tmax: np.ndarray, knobs: QueryKnobs, known=None,
                  visited: np.ndarray | None = None) -> Prediction:
    """proxy_query.predict in numpy, all pairs asked (the arguments are predict's)."""
    n = len(origin)
    best_t, best_i = known_hits(known, origin, direction, tmax)
    ray, inst = asked_boxes(world, remote, origin, direction, tmax, visited)
    if len(ray) == 0:
        return nothing_asked(best_t, best_i)
    # Box geometry for every (ray, instance) pair at once; only the nets run per mesh.
    q = box_queries(world.table, inst, origin[ray], direction[ray], tmax[ray])
    mesh = world.table.mesh[inst].astype(np.int64)
    a = answers(proxies, q, mesh, knobs)
    internal, inner_hits = closest_confident(ray, inst, q, a, best_t, best_i)
    uncertain, first_open = open_boxes(n, ray, inst, q, a, best_t)
    # An internal t is the surface nearest the box exit; the ray's first surface in that box
    # lies anywhere in (0, t]. Any internal hit that did not win may hide a nearer surface.
    ambiguous = inner_hits - internal > 0
    if knobs.exact_if_ambiguous:
        uncertain |= ambiguous
    asked = np.flatnonzero(a.has_proxy)
    asked = asked[np.argsort(mesh[asked], kind="stable")]  # grouped by mesh, pair order within
    return Prediction(best_t, best_i, uncertain, internal, ambiguous, first_open,
                      ray[asked].astype(np.int64), mesh[asked])


def asked_boxes(world, remote, origin, direction, tmax, visited):
    """(p,) ray rows and (p,) instances: the remote boxes each ray crosses before tmax, less
    those on shards it visited (what proxy_pairs.walk_queries walks for)."""
    ray, inst, _, _ = world.table.box_entries(origin, direction, tmax, remote)
    if visited is not None and len(ray):
        owner = world.owner[inst].astype(np.uint64)  # remote instances have one owner
        keep = (visited[ray] >> owner) & np.uint64(1) == 0
        ray, inst = ray[keep], inst[keep]
    return ray, inst


@dataclass(frozen=True)
class Answers:
    """Per (ray, box) pair: has_proxy (p,) bool (crossed, and its mesh has a proxy); unsure
    (p,) bool (in the band, or internal and near the origin); hit (p,) bool (a confident hit
    before tmax); t (p,) float32 world t of the predicted surface."""

    has_proxy: np.ndarray
    unsure: np.ndarray
    hit: np.ndarray
    t: np.ndarray


def answers(proxies: dict, q, mesh: np.ndarray, knobs: QueryKnobs) -> Answers:
    """Run each mesh's nets on its pairs and apply the external / internal rules."""
    p = len(mesh)
    vis = np.zeros(p, np.float32)
    t_proxy = np.full(p, np.inf)
    thr = np.zeros(p, np.float32)
    margin = np.zeros(p)  # world-t half-width of the internal case's unsure zone
    for m in np.unique(mesh[q.crosses]):
        proxy = proxies.get(int(m))
        if proxy is None:  # no proxy for this mesh: only exact forwarding can tell
            continue
        rows = np.flatnonzero(q.crosses & (mesh == m))
        thr[rows] = proxy.meta["threshold"] if knobs.threshold is None else knobs.threshold
        v, tp = proxy.query(q.point[rows], q.qdir[rows], min_visibility=float(thr[rows[0]]))
        vis[rows], t_proxy[rows] = v, tp / q.length[rows]
        p90 = proxy.meta.get("report", {}).get("depth_err_rel_p90", 0.0)
        margin[rows] = knobs.internal_margin * p90 * float(proxy.diag) / q.length[rows]
    has_proxy = q.crosses & np.isin(mesh, np.fromiter(proxies, np.int64, len(proxies)))
    return answer_rules(q, mesh, vis, t_proxy, thr, margin, has_proxy, knobs.band)


def answer_rules(q, mesh, vis, t_proxy, thr, margin, has_proxy, band) -> Answers:
    """The external / internal rules on the nets' answers: vis (p,) float32, t_proxy (p,)
    float64 world t (inf where not asked), thr (p,) float32, margin (p,) float64 world t,
    has_proxy (p,) bool; band (meshes,) float64."""
    near_origin = q.internal & (vis >= thr) & (np.abs(t_proxy - q.t_box) < margin)
    unsure = has_proxy & ((np.abs(vis - thr) < band[mesh]) | near_origin)
    hit = has_proxy & ~unsure & (vis >= thr)
    hit &= ~q.internal | (t_proxy <= q.t_box)  # internal: the surface lies behind the origin
    t = np.where(q.internal, q.t_box - t_proxy, q.t_box + t_proxy).astype(np.float32)
    return Answers(has_proxy, unsure, hit & (t < q.tmax), t)


def closest_confident(ray, inst, q, a: Answers, best_t, best_i):
    """Lower best_t / best_i (in place) to each ray's closest confident hit; ties go to the
    lowest instance. Returns internal (n,) bool (the winner is an internal answer) and
    inner_hits (n,) int64 (confident internal hits per ray)."""
    n = len(best_t)
    r, t, i, inner = ray[a.hit], a.t[a.hit], inst[a.hit], q.internal[a.hit]
    inner_hits = np.bincount(r[inner], minlength=n)
    order = np.lexsort((i, t, r))
    r, t, i, inner = r[order], t[order], i[order], inner[order]
    first = first_of_runs(r)
    r, t, i, inner = r[first], t[first], i[first], inner[first]
    better = t < best_t[r]
    best_t[r[better]], best_i[r[better]] = t[better], i[better]
    internal = np.zeros(n, bool)
    internal[r[better]] = inner[better]
    return internal, inner_hits


def open_boxes(n, ray, inst, q, a: Answers, best_t):
    """A box no proxy answers with confidence (in the band, or without a proxy) matters only
    if the ray enters it before its closest confident hit: only then can it hide a nearer
    surface. (Shadow rays use `uncertain` only where nothing occludes: best_t is inf.)
    Returns uncertain (n,) bool and first_open (n,) int32 (the open box entered first)."""
    uncertain = np.zeros(n, bool)
    first_open = np.full(n, -1, np.int32)
    t_enter = np.where(q.internal, 0.0, q.t_box)
    open_ = (a.unsure | (q.crosses & ~a.has_proxy)) & (t_enter < best_t[ray])
    uncertain[ray[open_]] = True
    o = np.flatnonzero(open_)
    o = o[np.lexsort((inst[o], t_enter[o], ray[o]))]  # per ray, nearest entry first
    lead = first_of_runs(ray[o])
    first_open[ray[o[lead]]] = inst[o[lead]]
    return uncertain, first_open


@dataclass(frozen=True)
class BoxQueries:
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
    tmax: np.ndarray


def box_queries(table, inst, origin, direction, tmax) -> BoxQueries:
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
    return BoxQueries(crosses, internal, t_box, point, qdir, np.linalg.norm(d, axis=1), tmax)
