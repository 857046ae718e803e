"""Neural-proxy intersection of rays with instance boxes this shard does not hold
(paper section 5): box entry point in local space, the visibility and depth nets, and
the external / internal cases of section 5.2."""

from __future__ import annotations

import weakref
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
    a hit. Per (ray, box) pair a proxy was asked about, grouped by base mesh in increasing
    order (pair order within a mesh: ray-major, then the order of the instances asked
    about): asked_ray (p,) int64 row, asked_mesh (p,) int64 base mesh (what the accuracy
    prediction counts)."""

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


@dataclass(frozen=True)
class Query:
    """One ray kind's questions for `predict_together`: origin (n, 3) float64 (or float32),
    direction (n, 3) float32 world, tmax (n,) float32, knobs, visited (n,) uint64 or None
    (as `predict`'s)."""

    origin: np.ndarray
    direction: np.ndarray
    tmax: np.ndarray
    knobs: QueryKnobs
    visited: np.ndarray | None = None


def predict(world: ShardWorld, proxies: dict, remote: np.ndarray, origin: np.ndarray,
            direction: np.ndarray, tmax: np.ndarray, knobs: QueryKnobs, known=None,
            visited: np.ndarray | None = None) -> Prediction:
    """origin (n, 3) float64 (or float32), direction (n, 3) float32 world; tmax (n,) float32;
    remote (m,) int32: the instances to ask proxies about; known: LocalGeometry of other
    remote instances, intersected exactly; visited: (n,) uint64 shard bitmask of each ray,
    whose shards' boxes are not asked about (their geometry was intersected exactly, and the
    ray carries what it found)."""
    preds, _ = predict_together(world, proxies, remote,
                                [Query(origin, direction, tmax, knobs, visited)], known)
    return preds[0]


def predict_together(world: ShardWorld, proxies: dict, remote: np.ndarray,
                     queries: list[Query], known=None) -> tuple[list[Prediction], int]:
    """`predict` of each query, with one walk and one call of each mesh's nets for all of
    them (a net call costs about 45 us whatever its rows: a step's secondary and shadow rays
    are asked together). A ray's answers do not depend on the other rays of its call
    (`Proxy.run`), so each Prediction is the one `predict` gives for its query alone.
    Returns the Predictions and the onnxruntime calls made."""
    sizes = [len(q.origin) for q in queries]
    off = np.r_[0, np.cumsum(sizes)]
    one = len(queries) == 1

    def joined(field, dtype):
        if one:
            return np.ascontiguousarray(getattr(queries[0], field), dtype)
        return np.concatenate([np.asarray(getattr(q, field), dtype) for q in queries])

    origin, direction = joined("origin", np.float64), joined("direction", np.float32)
    tmax = joined("tmax", np.float32)
    best_t, best_i = known_hits(known, origin, direction, tmax)
    table = world.table
    banks = [_bank(proxies, q.knobs, table.n_mesh) for q in queries]
    if off[-1] == 0 or len(remote) == 0:
        return [nothing_asked(best_t[a:b], best_i[a:b])
                for a, b in zip(off[:-1], off[1:], strict=True)], 0
    boxes, bvh, col_of, members, w2l, bounds, mesh_of = table.pair_inputs(remote)
    use_visited = any(q.visited is not None for q in queries)
    visited = np.zeros(0, np.uint64)
    if use_visited:  # a query without one has visited nothing
        visited = np.concatenate([np.zeros(n, np.uint64) if q.visited is None
                                  else np.asarray(q.visited, np.uint64)
                                  for q, n in zip(queries, sizes, strict=True)])
    # The crossed boxes and their local-space geometry in one walk; only the nets run per
    # mesh. Pairs whose local box the ray misses are dropped there: no rule looks at them.
    (ray, inst, mesh, has, internal, t_box, length, point, qdir, grouped,
     start) = proxy_pairs.walk_queries(
        origin, np.ascontiguousarray(direction, np.float64), tmax, boxes, bvh, col_of,
        members, world.owner, visited, use_visited, w2l, bounds, mesh_of, banks[0].has)
    # Pairs come ray-major: each query's are a slice, and each its own threshold.
    cut = np.searchsorted(ray, off)
    thr = np.concatenate([b.thr[mesh[cut[j]:cut[j + 1]]] for j, b in enumerate(banks)])
    vis, tp, calls = _ask_nets(banks[0], len(ray), grouped, start, point, qdir, thr)
    out = []
    for j, (q, bank) in enumerate(zip(queries, banks, strict=True)):
        a, b, r0, r1 = cut[j], cut[j + 1], off[j], off[j + 1]
        bt, bi = best_t[r0:r1], best_i[r0:r1]
        if a == b:
            out.append(nothing_asked(bt, bi))
            continue
        r = ray[a:b] - r0
        pairs = slice(a, b)
        internal_win, uncertain, ambiguous, first_open = proxy_pairs.decide(
            r, inst[pairs], mesh[pairs], np.ones(b - a, bool), internal[pairs], t_box[pairs],
            length[pairs], tmax[r0:r1][r], has[pairs], has[pairs], vis[pairs], tp[pairs],
            bank.thr, bank.band, bank.margin, bt, bi)
        # An internal t is the surface nearest the box exit; the ray's first surface in that
        # box lies anywhere in (0, t]. Any internal hit that did not win may hide a nearer
        # surface.
        if q.knobs.exact_if_ambiguous:
            uncertain |= ambiguous
        mine = grouped if one else grouped[(grouped >= a) & (grouped < b)]
        out.append(Prediction(bt, bi, uncertain, internal_win, ambiguous, first_open,
                              ray[mine] - r0, mesh[mine]))
    return out, calls


@dataclass(frozen=True)
class _Bank:
    """What `predict` reads per base mesh, for one proxies dict and one QueryKnobs (built
    once: a shard asks with the same two at every step). proxy (meshes,) the Proxy or None;
    has (meshes,) bool (a proxy answers for it); thr (meshes,) float32 visibility threshold;
    band (meshes,) float64; margin (meshes,) float64 internal margin in local units before
    dividing by the pair's length (world to local scale); line: every proxy uses the "line"
    encoding, whose float32 box constants (`Proxy.line_constants`) are stacked by mesh in
    consts: lo, hi, centre (meshes, 3), half, scale (meshes,), depth centre (meshes, 3)."""

    proxy: list
    has: np.ndarray
    thr: np.ndarray
    band: np.ndarray
    margin: np.ndarray
    line: bool
    consts: tuple


# knobs id -> (weak reference to the knobs, (meshes, proxies' ids), _Bank). An entry goes
# with its knobs (a policy's), so a pool that outlives jobs does not keep their proxies.
_BANKS: dict = {}


def _bank(proxies: dict, knobs: QueryKnobs, n_mesh: int) -> _Bank:
    which = (n_mesh, tuple((m, id(p)) for m, p in proxies.items()))
    got = _BANKS.get(id(knobs))
    if got is not None and got[0]() is knobs and got[1] == which:
        return got[2]
    proxy = [None] * n_mesh
    thr = np.zeros(n_mesh, np.float32)
    margin = np.zeros(n_mesh)
    has = np.zeros(n_mesh, bool)
    consts = [np.zeros((n_mesh, 3), np.float32), np.zeros((n_mesh, 3), np.float32),
              np.zeros((n_mesh, 3), np.float32), np.zeros(n_mesh, np.float32),
              np.zeros(n_mesh, np.float32), np.zeros((n_mesh, 3), np.float32)]
    line = True
    for m, p in proxies.items():
        if m >= n_mesh:
            continue
        proxy[m], has[m] = p, True
        thr[m] = p.meta["threshold"] if knobs.threshold is None else knobs.threshold
        p90 = p.meta.get("report", {}).get("depth_err_rel_p90", 0.0)
        margin[m] = knobs.internal_margin * p90 * float(p.diag)
        line = line and p.meta["encoding"] == "line"
        if line:
            for c, v in zip(consts, p.line_constants(), strict=True):
                c[m] = v
    bank = _Bank(proxy, has, thr, np.ascontiguousarray(knobs.band, np.float64), margin, line,
                 tuple(consts))
    key = id(knobs)
    _BANKS[key] = (weakref.ref(knobs, lambda _, key=key: _BANKS.pop(key, None)), which, bank)
    return bank


def _ask_nets(bank: _Bank, p: int, grouped: np.ndarray, start: np.ndarray, point, qdir,
              thr: np.ndarray):
    """Each mesh's nets on its pairs, mesh m's pair rows at grouped[start[m]:start[m + 1]]
    (pair order within a mesh), thr (p,) float32 each pair's visibility threshold: vis (p,)
    float32 (0 where not asked) and tp (p,) float32 the proxy's t in local units (inf where
    not asked or below the threshold), and the onnxruntime calls made. The "line" encoding
    of every mesh's pairs is one compiled pass before the nets and one after (the bits of
    Proxy.query, mesh by mesh)."""
    vis = np.zeros(p, np.float32)
    tp = np.full(p, np.inf, np.float32)
    rows = grouped
    if not len(rows):
        return vis, tp, 0
    groups = [(m, int(start[m]), int(start[m + 1])) for m in np.flatnonzero(np.diff(start))]
    calls = 0
    if not bank.line:
        for m, s, e in groups:
            sel = rows[s:e]
            low = float(thr[sel].min())  # depth where any query's threshold is reached
            v, t = bank.proxy[m].query(point[sel], qdir[sel], min_visibility=low)
            vis[sel], tp[sel] = v, np.where(v >= thr[sel], t, np.inf)
            calls += bank.proxy[m].calls(e - s) + bank.proxy[m].calls(int((v >= low).sum()))
        return vis, tp, calls
    from nprt.proxies import lineenc

    lo, hi, centre, half, scale, dcentre = bank.consts
    which = np.repeat(np.arange(len(start) - 1), np.diff(start))  # the mesh of each row
    x, on_box, shift = lineenc.line_inputs_rows(lo, hi, centre, half, which, rows, point, qdir)
    v = np.empty(len(rows), np.float32)
    for m, s, e in groups:
        v[s:e] = bank.proxy[m].run("visibility", x[s:e])
        calls += bank.proxy[m].calls(e - s)
    # The depth net runs where visibility reaches the threshold: those rows gathered once,
    # each mesh's still contiguous (the same rows, in the same order, as mesh by mesh).
    deep = v >= thr[rows]
    at = np.r_[0, np.cumsum(deep)][start]  # each mesh's first row among the deep ones
    x_deep = x[deep]
    y_deep = np.empty(len(x_deep), np.float32)
    for m, _, _ in groups:
        if at[m + 1] > at[m]:
            y_deep[at[m]:at[m + 1]] = bank.proxy[m].run("depth", x_deep[at[m]:at[m + 1]])
            calls += bank.proxy[m].calls(int(at[m + 1] - at[m]))
    y = np.zeros(len(rows), np.float32)
    y[deep] = y_deep
    vis[rows] = v
    tp[rows] = lineenc.line_depth_rows(scale, dcentre, which, rows, on_box, qdir, y, shift,
                                       deep)
    return vis, tp, calls


def nothing_asked(best_t: np.ndarray, best_i: np.ndarray) -> Prediction:
    """The Prediction of rays no proxy was asked about: only their known hits."""
    n, none = len(best_t), np.zeros(0, np.int64)
    return Prediction(best_t, best_i, np.zeros(n, bool), np.zeros(n, bool),
                      np.zeros(n, bool), np.full(n, -1, np.int32), none, none)


def known_hits(known, origin, direction, tmax):
    """(n,) float32 t and (n,) int32 instance of the closest exact hit among `known`."""
    n = len(origin)
    best_t = np.full(n, np.inf, np.float32)
    best_i = np.full(n, -1, np.int32)
    if known is not None and len(known.instances) and n:
        t, inst, _, _, _ = known.intersect_closest(origin, direction, tmax)
        hit = inst >= 0
        best_t[hit], best_i[hit] = t[hit], inst[hit]
    return best_t, best_i
