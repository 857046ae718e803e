"""Traversal policies: where each ray goes after this shard's local intersection.

- exact: Wald-style forwarding to the nearest unvisited box (the reference).
- proxy: the paper's method for secondary and shadow rays; primary rays stay exact.
- oracle: benchmark-only lower bound; forwards straight to the true closest-hit shard,
  using a full copy of the scene that only the benchmark may afford.
Targets are shard ids, or DONE (shade here / add the shadow contribution here).
"""

from __future__ import annotations

import numpy as np

from nprt.proxies.accuracy import counter_name, job_bands
from nprt.workers.routing.exact import (
    DONE,
    candidate_owner,
    nearest_unvisited,
    route_exact,
    route_exact_rows,
    route_shadow_exact,
)
from nprt.workers.routing.proxy_query import Query, QueryKnobs, predict, predict_together
from nprt.workers.runtime.protocol import EVERYWHERE
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import SplitStats
from nprt.workers.traversal.local import LocalGeometry, NearestRemote
from nprt.workers.wavefront.batch import (
    FLAG_EXACT,
    FLAG_INTERNAL,
    FLAG_TARGETED,
    SECONDARY,
    RayBatch,
    ShadowRayBatch,
)
from nprt.workers.wavefront.world import ShardWorld


class ExactPolicy:
    """cand_owner (m,) int32: what the shard's routing walks take (`candidate_owner`), so
    that `near`, their answer, spares route_* a second walk of the top level."""

    def __init__(self, world: ShardWorld, shard: int, remote: np.ndarray):
        self.world, self.shard, self.remote = world, shard, remote
        self.cand_owner = candidate_owner(world, remote)
        self._route_in = None
        # `_owner_of` by instance, DONE at index -1 (no hit, or a light: any negative inst)
        owner = np.asarray(world.owner, np.int32)
        self._owner_lut = np.append(
            np.where((owner == EVERYWHERE) | (owner == shard), DONE, owner), DONE
        ).astype(np.int32)

    @property
    def route_in(self) -> tuple:
        """The routing search's inputs (`nearest_unvisited`), made on first use."""
        if self._route_in is None:
            self._route_in = self.world.table.route_inputs(self.cand_owner)
        return self._route_in

    def route_rays(self, rays: RayBatch, stats: SplitStats, near: NearestRemote | None = None
                   ) -> tuple[RayBatch, np.ndarray]:
        return rays, route_exact(self.world, self.shard, self.remote, rays, near)

    def route_shadow(self, shadow: ShadowRayBatch, stats: SplitStats,
                     near: NearestRemote | None = None):
        """Returns (shadow rays still live, their targets)."""
        return shadow, route_shadow_exact(self.world, self.remote, shadow, near)

    def warm(self) -> None:
        """Compile (or load from numba's cache) what routing runs, before a timed pass:
        the routing walks are warmed by the shard's warm-up pass itself."""

    def _owner_of(self, inst: np.ndarray) -> np.ndarray:
        """(n,) int32 shard owning each hit instance (n,) int32, DONE when it is here (or
        none: -1, or a light's negative id)."""
        return self._owner_lut[np.maximum(inst, -1)]


class ProxyPolicy(ExactPolicy):
    """remote : (m,) int32 instances not held here (exact fallback forwarding covers all of
    them); known : those of them whose base mesh this shard holds, answered exactly; the
    rest (`modeled`) are answered by proxies.

    A secondary ray goes to the owner of its closest confident predicted hit, where that
    hit is final if real (a miss there falls back to exact forwarding). A ray that first
    enters a box no proxy answers with confidence goes to that box's owner instead, which
    intersects it exactly and asks the proxies again about the shards not visited yet: at
    band 1 this is exact forwarding, step for step.

    Bands are per mesh and kind: from the job's accuracy target and each proxy's held-out
    error curve (nprt.proxies.accuracy), or the hand-set band / shadow_band for all."""

    def __init__(self, world, shard, remote, proxies: dict, settings: RenderSettings,
                 known: LocalGeometry):
        super().__init__(world, shard, remote)
        self.modeled = remote[~np.isin(remote, known.instances)]
        self.known, self.proxies = known, proxies
        k = settings.proxy
        chosen = job_bands(proxies, k)
        # (2, meshes) secondary and shadow band by mesh index; 1 where no proxy answers.
        band = np.ones((2, max(int(world.table.mesh.max(initial=-1)),
                               max(proxies, default=-1)) + 1))
        for m, (b_sec, b_sh) in chosen.items():
            band[:, m] = b_sec, b_sh
        self.bands = chosen
        self.secondary = QueryKnobs(k.threshold, band[0], k.internal_margin,
                                    k.internal_ambiguous == "exact")
        # Shadow rays keep the paper's internal rule (margin 0).
        self.shadow = QueryKnobs(k.threshold, band[1], 0.0, k.internal_ambiguous == "exact")

    def warm(self) -> None:
        """The proxy query kernels too, which the shard's warm-up passes (two 4x4 blocks)
        may never reach: one ray through the centre of each of a few modeled boxes, from
        outside it, with both knobs (else a job's first proxy query compiles them, 20 s of
        CPU inside its render on a fresh cache)."""
        some = self.modeled[:4]
        if not len(some):
            return
        box = self.world.table.world_bounds[some]  # (n, 2, 3): lower, upper corner
        size = float(np.max(box[:, 1] - box[:, 0]))
        origin = (box[:, 0] + box[:, 1]) / 2 - [2.0 * size, 0.0, 0.0]
        direction = np.tile(np.float32([1, 0, 0]), (len(some), 1))
        tmax = np.full(len(some), 4.0 * size, np.float32)
        for knobs in (self.secondary, self.shadow):
            predict(self.world, self.proxies, self.modeled, origin, direction, tmax, knobs,
                    self.known, np.zeros(len(some), np.uint64))

    def route_rays(self, rays, stats):
        return self.route_together(rays, stats.tok, None, None, stats)[0]

    def route_shadow(self, shadow, stats):
        """Decided here: occluded if any proxy confidently predicts a hit before the light.
        Rays that cross a box of a mesh without a proxy, or (shadow_band > 0) a prediction
        inside the band, and have no confident occluder, fall back to exact forwarding."""
        return self.route_together(None, None, shadow, stats.tok, stats)[1]

    def route_together(self, rays, ray_tok, shadow, shadow_tok, stats: SplitStats):
        """`route_rays` of rays and `route_shadow` of shadow (either may be None), with one
        `predict_together` for both: one call of each mesh's nets, not two. ray_tok,
        shadow_tok: each batch's pass tokens (`SplitStats.bind`). Returns ((rays, target),
        (shadow, target)), None for a batch not given."""
        queries = []
        if rays is not None:
            stats.bind(ray_tok)
            flags, target, f = self._rays_before(rays, stats)
            if len(f):
                queries.append(Query(rays.origin[f], rays.direction[f], rays.tmax[f],
                                     self.secondary, rays.visited[f]))
        if shadow is not None and len(shadow):
            # A shadow ray forwarded here (shadow band) was intersected exactly on the
            # shards it visited: their boxes are not asked about again.
            queries.append(Query(shadow.origin, shadow.direction, shadow.tmax, self.shadow,
                                 shadow.visited))
        preds = []
        if queries:
            with stats.phase("proxy"):
                preds, calls = predict_together(self.world, self.proxies, self.modeled,
                                                queries, self.known)
            # A call serves every pass of the step: counted on the pass of the first row
            # of a batch that was asked about (bound here: the batch bound before may have
            # no rows), so that the passes add up to the calls made.
            stats.bind(ray_tok if rays is not None and len(f) else shadow_tok)
            stats.count("proxy_net_calls", np.zeros(calls, np.intp))
        routed_rays = routed_shadow = None
        if rays is not None:
            stats.bind(ray_tok)
            pred = preds.pop(0) if len(f) else None
            routed_rays = self._rays_after(rays, stats, flags, target, f, pred)
        if shadow is not None:
            stats.bind(shadow_tok)
            routed_shadow = self._shadow_after(shadow, stats, preds.pop(0) if preds else None)
        return routed_rays, routed_shadow

    def _rays_before(self, rays, stats):
        """Flags after a proxy's prediction is checked, targets (all DONE) and the rows (f,)
        int64 the proxies are asked about."""
        target = np.full(len(rays), DONE, np.int32)
        flags = rays.flags.copy()
        secondary = rays.kind == SECONDARY
        # Arrived where a proxy sent it: a real hit here is final, a miss is a misprediction.
        arrived = (flags & FLAG_TARGETED) != 0
        missed = arrived & ((rays.hit_inst < 0) | (self._owner_of(rays.hit_inst) != DONE))
        stats.count("proxy_mispredictions", missed)
        # The paper's internal case (origin inside the predicted box) counted on its own.
        stats.count("proxy_internal_mispredictions", missed & ((flags & FLAG_INTERNAL) != 0))
        flags[missed] |= FLAG_EXACT
        flags &= np.uint8(~(FLAG_TARGETED | FLAG_INTERNAL) & 0xFF)
        fresh = secondary & ~arrived & ((flags & FLAG_EXACT) == 0)
        return flags, target, np.flatnonzero(fresh)

    def _rays_after(self, rays, stats, flags, target, f, pred):
        """Targets of the rays from the proxies' answers pred for rows f (None: no row)."""
        if pred is not None:
            stats.count("proxy_queries", f)
            _count_asked(stats, "secondary", pred, f)
            stats.count("proxy_uncertain", f[pred.uncertain])
            stats.count("proxy_internal_ambiguous", f[pred.ambiguous])
            # An uncertain ray visits the owner of the first box it cannot trust, where that
            # box is intersected exactly and the proxies are asked again about the shards
            # not visited yet; one uncertain only for ambiguity falls back to exact forwarding.
            settle = pred.uncertain & (pred.first_open >= 0)
            flags[f[pred.uncertain & ~settle]] |= FLAG_EXACT
            target[f[settle]] = self.world.owner[pred.first_open[settle]]
            stats.count("proxy_settled", f[settle])
            go = ~pred.uncertain & (pred.inst >= 0)
            target[f[go]] = self.world.owner[pred.inst[go]]
            flags[f[go]] |= FLAG_TARGETED
            inner = go & pred.internal
            flags[f[inner]] |= FLAG_INTERNAL
            stats.count("proxy_targeted", f[go])
            stats.count("proxy_internal_targeted", f[inner])
            # No hit ahead: the closest is the one the ray carries, shaded by its owner.
            rest = f[~pred.uncertain & (pred.inst < 0)]
            target[rest] = self._owner_of(rays.hit_inst[rest])
        rays = rays.replace(flags=flags)
        # primary rays are always exact
        exact = (rays.kind != SECONDARY) | ((flags & FLAG_EXACT) != 0)
        if exact.any():
            target[exact] = route_exact_rows(self.world, self.shard, self.remote, rays,
                                             np.flatnonzero(exact), self.route_in)
        return rays, target

    def _shadow_after(self, shadow, stats, pred):
        """(shadow rays still live, their targets) from the proxies' answers pred (None:
        no shadow ray)."""
        if pred is None:
            return shadow, np.zeros(0, np.int32)
        stats.count("proxy_queries")
        _count_asked(stats, "shadow", pred, None)
        occluded = pred.inst >= 0
        stats.count("proxy_shadow_occluded", occluded)
        stats.count_hops(shadow.hops, occluded)  # they finish here
        stats.count("proxy_shadow_uncertain", ~occluded & pred.uncertain)
        shadow = shadow.take(~occluded)
        target = np.full(len(shadow), DONE, np.int32)
        unknown = pred.uncertain[~occluded]
        if unknown.any():  # route_shadow_exact of these rows, without a copy of the batch
            u = np.flatnonzero(unknown)
            target[u] = nearest_unvisited(self.world, self.remote, shadow.origin[u],
                                          shadow.direction[u], shadow.tmax[u],
                                          shadow.visited[u], self.route_in)
        return shadow, target


def _count_asked(stats: SplitStats, kind: str, pred, rows: np.ndarray | None) -> None:
    """Box queries per mesh (what the accuracy prediction weighs each proxy's error by);
    rows (n,) maps the prediction's rays to the bound batch (None: they are its rows). The
    pairs come grouped by mesh: a slice a mesh, not a mask."""
    mesh = pred.asked_mesh
    if not len(mesh):
        return
    asked = pred.asked_ray if rows is None else rows[pred.asked_ray]
    cut = [0, *(np.flatnonzero(mesh[1:] != mesh[:-1]) + 1).tolist(), len(mesh)]
    for s, e in zip(cut[:-1], cut[1:], strict=True):
        stats.count(counter_name(kind, mesh[s]), asked[s:e])


class OraclePolicy(ExactPolicy):
    """Knows every true closest hit (full scene on every shard): the transfer floor."""

    def __init__(self, world, shard, remote, everything: LocalGeometry):
        super().__init__(world, shard, remote)
        self.everything = everything

    def route_rays(self, rays, stats):
        target = np.full(len(rays), DONE, np.int32)
        arrived = (rays.flags & FLAG_TARGETED) != 0
        fresh = (rays.kind == SECONDARY) & ~arrived
        exact = ~fresh & ~arrived
        if fresh.any():
            f = np.flatnonzero(fresh)
            _, inst, _, _, _ = self.everything.intersect_closest(
                rays.origin[f], rays.direction[f], rays.tmax[f])
            target[f] = self._owner_of(inst)
            rays = rays.replace(flags=rays.flags | (fresh * FLAG_TARGETED).astype(np.uint8))
        if exact.any():
            target[exact] = route_exact_rows(self.world, self.shard, self.remote, rays,
                                             np.flatnonzero(exact), self.route_in)
        done_here = target == DONE
        target[done_here] = self._owner_of(rays.hit_inst[done_here])
        return rays, target

    def route_shadow(self, shadow, stats):
        """Sent to the shard of the nearest true occluder (which drops it), else done."""
        _, inst, _, _, _ = self.everything.intersect_closest(
            shadow.origin, shadow.direction, shadow.tmax)
        return shadow, self._owner_of(inst)
