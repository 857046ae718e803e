"""Neural-proxy intersection of rays with instance boxes this shard does not hold
(paper section 5): box entry point in local space, the visibility and depth nets, and
the external / internal cases of section 5.2."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nprt.workers.routing import proxy_pairs
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
    inside the band, or an internal one within the internal margin of the origin, is never
    a hit. Per (ray, box) pair a proxy was asked about: asked_ray (p,) int64 row,
    asked_mesh (p,) int64 base mesh (what the accuracy prediction counts)."""

    t: np.ndarray
    inst: np.ndarray
    uncertain: np.ndarray
    internal: np.ndarray
    ambiguous: np.ndarray
    first_open: np.ndarray
    asked_ray: np.ndarray
    asked_mesh: np.ndarray


@dataclass(frozen=True)
class QueryKnobs:
    """How one ray kind trusts the proxies. threshold None: each proxy's own (calibrated at
    training); band : (meshes,) float64 confidence band per base mesh; internal_margin: a
    confident internal answer whose surface lies within this fraction of the proxy's held-out
    p90 depth error of the origin is unsure (0 keeps the paper's rule); exact_if_ambiguous:
    Prediction.ambiguous rays are uncertain."""

    threshold: float | None
    band: np.ndarray
    internal_margin: float = 0.0
    exact_if_ambiguous: bool = True


def predict(world: ShardWorld, proxies: dict, remote: np.ndarray, origin: np.ndarray,
            direction: np.ndarray, tmax: np.ndarray, knobs: QueryKnobs, known=None,
            visited: np.ndarray | None = None) -> Prediction:
    """origin (n, 3) float64 (or float32), direction (n, 3) float32 world; tmax (n,) float32;
    remote (m,) int32: the instances to ask proxies about; known: LocalGeometry of other
    remote instances, intersected exactly; visited: (n,) uint64 shard bitmask of each ray,
    whose shards' boxes are not asked about (their geometry was intersected exactly, and the
    ray carries what it found)."""
    best_t, best_i, ray, inst = asked_pairs(world, remote, origin, direction, tmax, known,
                                            visited)
    if len(ray) == 0:
        return nothing_asked(best_t, best_i)
    table = world.table
    tmax = np.ascontiguousarray(tmax, np.float32)
    # Box geometry for every (ray, instance) pair at once; only the nets run per mesh.
    crosses, internal, t_box, length, point, qdir = proxy_pairs.box_queries(
        ray, inst.astype(np.int32, copy=False), np.ascontiguousarray(origin, np.float64),
        np.ascontiguousarray(direction, np.float64), tmax, table.kernel_arrays()[2],
        np.ascontiguousarray(table.local_bounds, np.float64))
    mesh = table.mesh[inst].astype(np.int64)
    thr_m, margin_m, has_m = _mesh_constants(proxies, knobs, table.n_mesh)
    has = crosses & has_m[mesh]  # crossed, and its mesh has a proxy
    vis, tp = _ask_nets(proxies, mesh, has, point, qdir, thr_m)
    internal_win, uncertain, ambiguous, first_open = proxy_pairs.decide(
        ray, inst, mesh, crosses, internal, t_box, length, tmax[ray], has, has, vis, tp,
        thr_m, np.asarray(knobs.band, np.float64), margin_m, best_t, best_i)
    # An internal t is the surface nearest the box exit; the ray's first surface in that box
    # lies anywhere in (0, t]. Any internal hit that did not win may hide a nearer surface.
    if knobs.exact_if_ambiguous:
        uncertain |= ambiguous
    return Prediction(best_t, best_i, uncertain, internal_win, ambiguous, first_open,
                      ray[has].astype(np.int64), mesh[has])


def _mesh_constants(proxies: dict, knobs: QueryKnobs, n_mesh: int):
    """Per base mesh: thr (meshes,) float32 visibility threshold, margin (meshes,) float64
    internal margin in local units before dividing by the pair's length (world to local
    scale), has (meshes,) bool (a proxy answers for it)."""
    thr = np.zeros(n_mesh, np.float32)
    margin = np.zeros(n_mesh)
    has = np.zeros(n_mesh, bool)
    for m, proxy in proxies.items():
        if m >= n_mesh:
            continue
        has[m] = True
        thr[m] = proxy.meta["threshold"] if knobs.threshold is None else knobs.threshold
        p90 = proxy.meta.get("report", {}).get("depth_err_rel_p90", 0.0)
        margin[m] = knobs.internal_margin * p90 * float(proxy.diag)
    return thr, margin, has


def _ask_nets(proxies: dict, mesh: np.ndarray, ask: np.ndarray, point, qdir, thr_m):
    """Each mesh's nets on its pairs where `ask` (p,) bool, in pair order: vis (p,) float32
    (0 where not asked) and tp (p,) float32 the proxy's t in local units (inf where not asked
    or below the threshold). The "line" encoding of every mesh's pairs is one compiled pass
    before the nets and one after (the bits of Proxy.query, mesh by mesh)."""
    p = len(mesh)
    vis = np.zeros(p, np.float32)
    tp = np.full(p, np.inf, np.float32)
    rows = np.flatnonzero(ask)
    if not len(rows):
        return vis, tp
    rows = rows[np.argsort(mesh[rows], kind="stable")]  # grouped by mesh, pair order within
    cut = np.r_[0, np.flatnonzero(np.diff(mesh[rows])) + 1, len(rows)]
    group = [proxies[int(m)] for m in mesh[rows[cut[:-1]]]]
    if any(g.meta["encoding"] != "line" for g in group):
        for proxy, s, e in zip(group, cut[:-1], cut[1:], strict=True):
            sel = rows[s:e]
            vis[sel], tp[sel] = proxy.query(point[sel], qdir[sel],
                                            min_visibility=float(thr_m[mesh[sel[0]]]))
        return vis, tp
    from nprt.proxies import lineenc

    consts = [g.line_constants() for g in group]
    which = np.repeat(np.arange(len(group)), np.diff(cut))
    x, on_box, shift = lineenc.line_inputs_rows(
        *(np.array([c[k] for c in consts]) for k in range(4)), which, rows, point, qdir)
    v = np.empty(len(rows), np.float32)
    y = np.zeros(len(rows), np.float32)
    deep = np.zeros(len(rows), bool)  # the depth net ran
    for proxy, s, e in zip(group, cut[:-1], cut[1:], strict=True):
        v[s:e] = proxy.run("visibility", x[s:e])
        sel = s + np.flatnonzero(v[s:e] >= thr_m[mesh[rows[s]]])
        y[sel] = proxy.run("depth", x[sel])
        deep[sel] = True
    vis[rows] = v
    tp[rows] = lineenc.line_depth_rows(np.array([c[4] for c in consts]),
                                       np.array([c[5] for c in consts]), which, rows, on_box,
                                       qdir, y, shift, deep)
    return vis, tp


def asked_pairs(world, remote, origin, direction, tmax, known, visited):
    """What `predict` starts from (its arguments): (n,) float32 t and (n,) int32 instance of
    each ray's closest exact hit among `known`, and the (p,) ray rows and (p,) instances of
    the (ray, box) pairs the proxies are asked about."""
    best_t, best_i = _known_hits(known, origin, direction, tmax)
    ray, inst = _asked_boxes(world, remote, origin, direction, tmax, visited)
    return best_t, best_i, ray, inst


def nothing_asked(best_t: np.ndarray, best_i: np.ndarray) -> Prediction:
    """The Prediction of rays no proxy was asked about: only their known hits."""
    n, none = len(best_t), np.zeros(0, np.int64)
    return Prediction(best_t, best_i, np.zeros(n, bool), np.zeros(n, bool),
                      np.zeros(n, bool), np.full(n, -1, np.int32), none, none)


def _known_hits(known, origin, direction, tmax):
    """(n,) float32 t and (n,) int32 instance of the closest exact hit among `known`."""
    n = len(origin)
    best_t = np.full(n, np.inf, np.float32)
    best_i = np.full(n, -1, np.int32)
    if known is not None and len(known.instances) and n:
        t, inst, _, _, _ = known.intersect_closest(origin, direction, tmax)
        hit = inst >= 0
        best_t[hit], best_i[hit] = t[hit], inst[hit]
    return best_t, best_i


def _asked_boxes(world, remote, origin, direction, tmax, visited):
    """(p,) ray rows and (p,) instances: the remote boxes each ray crosses before tmax, less
    those on shards it visited."""
    ray, inst, _, _ = world.table.box_entries(origin, direction, tmax, remote)
    if visited is not None and len(ray):
        owner = world.owner[inst].astype(np.uint64)  # remote instances have one owner
        keep = (visited[ray] >> owner) & np.uint64(1) == 0
        ray, inst = ray[keep], inst[keep]
    return ray, inst
