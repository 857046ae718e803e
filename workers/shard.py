"""The Shard actor: one slice of the scene's geometry in Embree, the replicated
instance table and lights, and the traversal policy. A plain class; the coordinator
applies ray.remote where it starts it.

Every call takes parcels of rays that other shards sent here and returns one parcel
per target shard, so batches move shard to shard through the object store while the
coordinator only routes references. Film and statistics are kept per pass and handed
back by `finish_pass`, so a pass that fails can be dropped without counting it twice.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field

import numpy as np

from scene.model import Mesh
from workers.batch import FLAG_SHADE, KIND_NAMES, SHADOW, RayBatch, ShadowRayBatch
from workers.geometry import MeshGeometry
from workers.integrator import PathIntegrator
from workers.local import LocalGeometry
from workers.passes import Pass
from workers.policies import ExactPolicy, OraclePolicy, ProxyPolicy
from workers.routing import DONE, nearest_unvisited, visited_bit
from workers.settings import RenderSettings
from workers.stats import RenderStats
from workers.tracer import resolve_closest
from workers.world import EVERYWHERE, ShardWorld

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShardConfig:
    shard_id: int
    k: int
    settings: RenderSettings


@dataclass
class Parcel:
    """Rays travelling to one shard. Either part may be empty."""

    rays: RayBatch
    shadow: ShadowRayBatch
    sent_at: float = field(default_factory=time.time)  # wall clock, for transfer wait

    @property
    def nbytes(self) -> int:
        return self.rays.nbytes + self.shadow.nbytes

    def __len__(self) -> int:
        return len(self.rays) + len(self.shadow)


@dataclass
class Manifest:
    """The small part of a call's result that the coordinator reads: rays per target."""

    shard: int
    counts: list[int]  # (k,) rays + shadow rays sent to each shard


@dataclass
class _PassState:
    sums: np.ndarray  # (n_pixels, 3) float64
    stats: RenderStats = field(default_factory=RenderStats)
    calls: int = 0  # generate/process calls seen; fewer than sent means a restart lost state


class Shard:
    def __init__(self, config: ShardConfig, world: ShardWorld, meshes: dict[int, Mesh],
                 proxies: dict | None = None, all_meshes: dict[int, Mesh] | None = None):
        """meshes: the geometry this shard owns (plus replicated meshes); proxies: mesh index
        -> proxies.inference.Proxy for remote meshes (proxy mode); all_meshes: the whole
        scene, for the benchmark-only oracle policy."""
        self.config, self.world = config, world
        self.id, self.k, self.s = config.shard_id, config.k, config.settings
        self.bit = visited_bit(self.id)
        self.meshes = meshes
        geometry = {i: MeshGeometry(m) for i, m in meshes.items()}
        local = world.local_instances(self.id)
        self.local = LocalGeometry(geometry, world.table, local)
        is_local = np.zeros(len(world.table), bool)
        is_local[local] = True
        self.remote = np.flatnonzero(~is_local).astype(np.int32)
        # Instances with one owner (not replicated): where camera rays may start.
        self.owned = np.flatnonzero(world.owner != EVERYWHERE).astype(np.int32)
        self.policy = self._make_policy(proxies or {}, all_meshes, geometry)
        self.integrator = PathIntegrator(self.s, world.camera, meshes, world.materials,
                                         world.table, world.lights)
        self.passes: dict[int, _PassState] = {}
        log.info("%r started in pid %d", self, os.getpid())

    def _make_policy(self, proxies, all_meshes, geometry):
        mode = self.s.mode
        if mode == "proxy":
            # Remote instances of a base mesh held here (a mesh split across shards) are
            # intersected exactly with it, not through a proxy.
            held = np.isin(self.world.table.mesh[self.remote], list(geometry))
            known = LocalGeometry(geometry, self.world.table, self.remote[held])
            return ProxyPolicy(self.world, self.id, self.remote, proxies, self.s, known)
        if mode == "oracle":
            if all_meshes is None:
                raise ValueError("the oracle policy needs all_meshes (the whole scene)")
            full = {i: geometry.get(i) or MeshGeometry(m) for i, m in all_meshes.items()}
            everything = LocalGeometry(full, self.world.table,
                                       np.arange(len(self.world.table), dtype=np.int32))
            return OraclePolicy(self.world, self.id, self.remote, everything)
        return ExactPolicy(self.world, self.id, self.remote)

    def __repr__(self) -> str:
        if "local" not in self.__dict__:  # Ray prints a shard whose __init__ raised
            return f"Shard({self.__dict__.get('id', '?')}, not started)"
        return (f"Shard({self.id}/{self.k}, {len(self.meshes)} meshes, "
                f"{len(self.local.instances)} local instances)")

    def ready(self) -> dict:
        return {"shard": self.id, "pid": os.getpid(),
                "geometry_bytes": int(sum(m.nbytes for m in self.meshes.values()))}

    # -- calls from the coordinator -------------------------------------------------

    def generate(self, p: Pass) -> list:
        """This shard's share of a tile's camera rays, traced as far as they go here.

        Every shard generates the whole tile (deterministic and cheap) and keeps the rays
        whose first instance box it owns, so no camera ray moves just to reach its first
        candidate; rays that enter no owned box start on the tile's shard, p.index % k."""
        st = self._state(p)
        with st.stats.phase("generate"):
            rays = self.integrator.primary(p)
            first = nearest_unvisited(self.world, self.owned, rays.origin, rays.direction,
                                      rays.tmax, np.zeros(len(rays), np.uint64))
            mine = (first == self.id) | ((first == DONE) & (p.index % self.k == self.id))
            rays = rays.take(mine)
        return self._run(p, st, rays, ShadowRayBatch.empty())

    def process(self, p: Pass, *parcels: Parcel) -> list:
        """Rays that other shards sent here."""
        st = self._state(p)
        st.stats.phase_s["transfer_wait"] += max(0.0, time.time() - min(x.sent_at for x in parcels))
        rays = RayBatch.concat([x.rays for x in parcels])
        shadow = ShadowRayBatch.concat([x.shadow for x in parcels])
        return self._run(p, st, rays, shadow)

    def finish_pass(self, index: int) -> tuple[np.ndarray | None, dict, int]:
        """(film sums, stats, calls this incarnation ran for the pass)."""
        st = self.passes.pop(index, None)
        if st is None:
            return None, RenderStats().to_dict(), 0
        return st.sums, st.stats.to_dict(), st.calls

    def abort_pass(self, index: int) -> None:
        self.passes.pop(index, None)

    # -- the wavefront inside one call ---------------------------------------------

    def _state(self, p: Pass) -> _PassState:
        if p.index not in self.passes:
            self.passes[p.index] = _PassState(np.zeros((p.n_pixels, 3)))
        self.passes[p.index].calls += 1
        return self.passes[p.index]

    def _run(self, p: Pass, st: _PassState, rays: RayBatch, shadow: ShadowRayBatch) -> list:
        stats = st.stats
        out_rays = [[] for _ in range(self.k)]
        out_shadow = [[] for _ in range(self.k)]
        while len(rays) or len(shadow):
            if len(rays):
                settled = (rays.flags & FLAG_SHADE) != 0
                arrived, rays = rays.take(settled), rays.take(~settled)
                stats.count_rays(rays.kind)
                rays = rays.replace(visited=rays.visited | self.bit)
                with stats.phase("local_intersect"):
                    rays = resolve_closest(rays, self.local, self.world.lights)
                with stats.phase("top_level"):
                    rays, target = self.policy.route_rays(rays, stats)
                # Rays going to their hit's owner only to be shaded are not re-intersected:
                # a second Embree call with tmax == t may pick a different triangle on an edge.
                final = (target != DONE) & (rays.hit_inst >= 0) & \
                    (target == self.world.owner[np.maximum(rays.hit_inst, 0)])
                rays = rays.replace(flags=rays.flags | (final * FLAG_SHADE).astype(np.uint8))
                self._send(rays, target, out_rays)
                done = RayBatch.concat([arrived, rays.take(target == DONE)])
                done = done.replace(flags=done.flags & np.uint8(~FLAG_SHADE & 0xFF))
                stats.count_hops(done.hops)
                with stats.phase("shade"):
                    shaded = self.integrator.shade(done)
                self._splat(p, st, shaded.pixel, shaded.rgb)
                shadow = ShadowRayBatch.concat([shadow, shaded.shadow])
                rays = shaded.secondary
            if len(shadow):
                stats.count_rays(SHADOW, len(shadow))
                shadow = shadow.replace(visited=shadow.visited | self.bit)
                with stats.phase("local_intersect"):
                    free = ~self.local.intersect_occluded(shadow.origin, shadow.direction,
                                                          shadow.tmax)
                stats.count_hops(shadow.hops[~free])  # occluded here: these rays finish too
                shadow = shadow.take(free)
                with stats.phase("top_level"):
                    shadow, target = self.policy.route_shadow(shadow, stats)
                self._send(shadow, target, out_shadow)
                done = shadow.take(target == DONE)
                stats.count_hops(done.hops)
                self._splat(p, st, done.pixel, done.contribution.astype(np.float64))
                shadow = ShadowRayBatch.empty()
        parcels = []
        for t in range(self.k):
            parcel = Parcel(RayBatch.concat(out_rays[t]), ShadowRayBatch.concat(out_shadow[t]))
            for kind, batch in (("rays", parcel.rays), ("shadow", parcel.shadow)):
                if len(batch):
                    self._count_transfer(stats, kind, batch)
            parcels.append(parcel if len(parcel) else None)
        manifest = Manifest(self.id, [0 if x is None else len(x) for x in parcels])
        return [manifest, *parcels]

    def _send(self, batch, target: np.ndarray, out: list) -> None:
        away = target != DONE
        if not away.any():
            return
        moving = batch.take(away)
        moving = moving.replace(hops=moving.hops + np.uint8(1))
        t = target[away]
        for dest in np.unique(t):
            out[int(dest)].append(moving.take(t == dest))

    @staticmethod
    def _count_transfer(stats: RenderStats, kind: str, batch) -> None:
        if kind == "shadow":
            stats.count_transfer("shadow", len(batch), batch.nbytes)
            return
        per_row = batch.nbytes // len(batch)
        for k, c in enumerate(np.bincount(batch.kind, minlength=2)[:2]):
            if c:
                stats.count_transfer(KIND_NAMES[k], int(c), int(c) * per_row)

    def _splat(self, p: Pass, st: _PassState, pixel: np.ndarray, rgb: np.ndarray) -> None:
        if len(pixel) == 0:
            return
        idx = p.local_index(pixel, self.s.width)
        for c in range(3):
            st.sums[:, c] += np.bincount(idx, weights=rgb[:, c], minlength=p.n_pixels)
