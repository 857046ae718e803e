"""The Shard actor: one slice of the scene's geometry in Embree, the replicated
instance table and lights, and the traversal policy. A plain class: the pool starts
it through `nprt.workers.runtime.remote.ShardActor`, so the driver never imports this module.

Every call carries work of several passes (camera rays to generate, parcels that other
shards sent here) and returns one object per target shard, so batches move shard to
shard through the object store while the coordinator only routes references. Film and
statistics are kept per pass attempt (a token) and handed back by `collect`, so a pass
that fails can be dropped without counting it twice. The geometry outlives a job: a
pool reuses the shard, and each call brings its job's settings.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field

import numpy as np

from nprt.scene.model import Mesh
from nprt.workers.passes import Pass
from nprt.workers.routing.exact import DONE, nearest_unvisited, visited_bit
from nprt.workers.routing.policies import ExactPolicy, OraclePolicy, ProxyPolicy
from nprt.workers.runtime.protocol import EVERYWHERE, Manifest, MeshRequest, ShardConfig, WorkItem
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats, SplitStats
from nprt.workers.traversal.closest import resolve_closest
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.wavefront.batch import FLAG_SHADE, KIND_NAMES, SHADOW, RayBatch, ShadowRayBatch
from nprt.workers.wavefront.integrator import PathIntegrator
from nprt.workers.wavefront.world import ShardWorld

log = logging.getLogger(__name__)


@dataclass
class Parcel:
    """Rays of one pass attempt travelling to one shard. Either part may be empty."""

    rays: RayBatch
    shadow: ShadowRayBatch
    sent_at: float = field(default_factory=time.time)  # wall clock, for transfer wait

    @property
    def nbytes(self) -> int:
        return self.rays.nbytes + self.shadow.nbytes

    def __len__(self) -> int:
        return len(self.rays) + len(self.shadow)


@dataclass
class _PassState:
    token: int
    sums: np.ndarray  # (n_pixels, 3) float64
    stats: RenderStats = field(default_factory=RenderStats)
    calls: int = 0  # calls seen for this token; fewer than sent means a restart lost state


class _Call:
    """The pass attempts of one call. A ray's pixel names its tile, and a call holds one
    attempt per tile, so `tok` finds each ray's attempt without a column on the wire."""

    def __init__(self, s: RenderSettings, passes: list[Pass], states: list[_PassState]):
        self.s, self.passes, self.states = s, passes, states
        self.tokens = [st.token for st in states]
        self.stats = SplitStats([st.stats for st in states])
        self.tiles_x = -(-s.width // s.tile_size)
        tiles = self.tiles_x * -(-s.height // s.tile_size)
        self.lookup = np.full(tiles, -1, np.int64)  # tile -> index into states
        for i, p in enumerate(passes):
            tile = (p.y0 // s.tile_size) * self.tiles_x + p.x0 // s.tile_size
            if self.lookup[tile] >= 0:
                raise ValueError(f"passes {passes[self.lookup[tile]].index} and {p.index} "
                                 f"share tile {tile}: one call takes one pass per tile")
            self.lookup[tile] = i

    def tok(self, pixel: np.ndarray) -> np.ndarray:
        """pixel (n,) uint32 -> (n,) int64 index of its attempt in this call."""
        pixel = pixel.astype(np.int64)
        ts = self.s.tile_size
        tile = (pixel // self.s.width // ts) * self.tiles_x + (pixel % self.s.width) // ts
        return self.lookup[tile]

    def split(self, batch) -> list:
        """(t,) the rows of batch belonging to each attempt."""
        if len(self.states) == 1:
            return [batch]
        tok = self.tok(batch.pixel)
        return [batch.take(tok == i) for i in range(len(self.states))]

    def splat(self, pixel: np.ndarray, rgb: np.ndarray) -> None:
        """Add rgb (n, 3) float64 to each attempt's tile film."""
        if len(pixel) == 0:
            return
        tok = self.tok(pixel)
        for i in np.unique(tok):
            st, p = self.states[i], self.passes[i]
            mine = tok == i
            idx = p.local_index(pixel[mine], self.s.width)
            for c in range(3):
                st.sums[:, c] += np.bincount(idx, weights=rgb[mine, c], minlength=p.n_pixels)


class Shard:
    def __init__(self, config: ShardConfig, world: ShardWorld,
                 meshes: dict[int, Mesh] | MeshRequest,
                 proxies: dict | None = None,
                 all_meshes: dict[int, Mesh] | MeshRequest | None = None):
        """meshes: the geometry this shard owns (plus replicated meshes), or the request
        it loads them by; proxies: mesh index -> nprt.proxies.inference.Proxy for remote meshes
        (proxy mode); all_meshes: the whole scene, for the benchmark-only oracle policy."""
        self.config, self.world = config, world
        self.id, self.k = config.shard_id, config.k
        self.bit = visited_bit(self.id)
        t0 = time.perf_counter()
        if isinstance(meshes, MeshRequest):
            meshes = meshes.load()
        if isinstance(all_meshes, MeshRequest):
            rest = [i for i in all_meshes.indices if i not in meshes]
            all_meshes = {**all_meshes.source.load_meshes(rest), **meshes}
        self.load_s = time.perf_counter() - t0
        self.meshes = meshes
        self.geometry = {i: MeshGeometry(m) for i, m in meshes.items()}
        self._place()
        self._proxies, self._all_meshes = proxies or {}, all_meshes
        self.s: RenderSettings | None = None
        self.configure(config.settings)
        self.passes: dict[int, _PassState] = {}
        log.info("%r started in pid %d", self, os.getpid())

    def _place(self) -> None:
        """What follows from the world's instance table: the instances intersected here."""
        local = self.world.local_instances(self.id)
        self.local = LocalGeometry(self.geometry, self.world.table, local)
        is_local = np.zeros(len(self.world.table), bool)
        is_local[local] = True
        self.remote = np.flatnonzero(~is_local).astype(np.int32)
        # Instances with one owner (not replicated): where camera rays may start.
        self.owned = np.flatnonzero(self.world.owner != EVERYWHERE).astype(np.int32)

    def set_world(self, world: ShardWorld) -> int:
        """Show another frame: swap the instance table and lights, keep the geometry (Embree
        scenes) and proxies. The world must place the same meshes on the same shards (the
        same owner and instance meshes), so what this shard holds stays right. Returns
        the instance count."""
        old = self.world
        if not (np.array_equal(world.owner, old.owner)
                and np.array_equal(world.table.mesh, old.table.mesh)):
            raise ValueError(f"{self!r}: a new frame must keep each instance's mesh and owner")
        self.world = world
        self._place()
        settings, self.s = self.s, None
        self.configure(settings)  # the policy and integrator read the table and lights
        return len(world.table)

    def configure(self, settings: RenderSettings) -> None:
        """Per-job settings (seed, bounces, knobs): cheap, the geometry stays."""
        if settings == self.s:
            return
        if (settings.shards or 1) != self.k or settings.mode != self.config.settings.mode:
            raise ValueError(f"{self!r} holds a K={self.k} {self.config.settings.mode!r} "
                             f"placement, not K={settings.shards} {settings.mode!r}")
        self.s = settings
        self.policy = self._make_policy(self._proxies, self._all_meshes, self.geometry)
        self.integrator = PathIntegrator(settings, self.world.camera, self.meshes,
                                         self.world.materials, self.world.table,
                                         self.world.lights)

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
        import ray

        node = ray.util.get_node_ip_address() if ray.is_initialized() else "local"
        return {"shard": self.id, "pid": os.getpid(), "node": node,
                "geometry_bytes": int(sum(m.nbytes for m in self.meshes.values())),
                "meshes": sorted(self.meshes), "load_s": round(self.load_s, 4)}

    def warm(self) -> float:
        """Trace a 4x4-pixel, 1-sample pass and drop it, so every kernel is compiled (or
        loaded from numba's cache) before the first timed pass. Returns seconds taken."""
        t0 = time.perf_counter()
        s = self.config.settings
        p = Pass(-1, 0, 0, min(4, s.width), min(4, s.height), 0, 1)
        self.work(s, [WorkItem(-1, p, True, 0)])
        self.passes.pop(-1, None)
        return time.perf_counter() - t0

    # -- calls from the coordinator -------------------------------------------------

    def work(self, settings: RenderSettings, items: list[WorkItem],
             *parcels: dict[int, Parcel]) -> list:
        """Run every item's rays, merged into one wavefront (batches as large as the call
        allows), as far as they go here. Items must be on distinct tiles: a ray's pixel
        names its pass. Returns [Manifest, out_0 .. out_{k-1}], out_t a {token: Parcel} of
        the rays going to shard t (None if none)."""
        t0 = time.perf_counter()
        self.configure(settings)
        states = [self._state(item) for item in items]
        call = _Call(self.s, [item.pass_ for item in items], states)
        rays, got = [], []
        at = 0
        for item, st in zip(items, states, strict=True):
            if item.generate:
                with st.stats.phase("generate"):
                    rays.append(self._generate(item.pass_))
            # Each argument is one shard's {token: Parcel} output; a call may get it once
            # per token it holds.
            got += [x[item.token] for x in parcels[at:at + item.n_parcels]]
            at += item.n_parcels
        bytes_in = sum(x.nbytes for x in got)
        if got:
            call.stats.times.phase_s["transfer_wait"] += max(
                0.0, time.time() - min(x.sent_at for x in got))
        out = self._run(call, RayBatch.concat(rays + [x.rays for x in got]),
                        ShadowRayBatch.concat([x.shadow for x in got]))
        counts = {item.token: [0] * self.k for item in items}
        bytes_out = 0
        for t, by_token in enumerate(out):
            for token, parcel in by_token.items():
                counts[token][t] = len(parcel)
                bytes_out += parcel.nbytes
        manifest = Manifest(self.id, counts, time.perf_counter() - t0, bytes_in, bytes_out)
        return [manifest, *[o or None for o in out]]

    def collect(self, tokens: list[int]) -> tuple:
        """((token, film sums (n_pixels, 3) f64 or None, stats dict, calls seen), ...) for
        finished passes; their state is dropped here."""
        out = []
        for token in tokens:
            st = self.passes.pop(token, None)
            if st is None:
                out.append((token, None, RenderStats().to_dict(), 0))
            else:
                out.append((token, st.sums, st.stats.to_dict(), st.calls))
        return tuple(out)

    def abort(self, tokens: list[int]) -> None:
        """Drop the state of pass attempts that will be re-run."""
        for token in tokens:
            self.passes.pop(token, None)

    def _generate(self, p: Pass) -> RayBatch:
        """This shard's share of a tile's camera rays.

        Every shard generates the whole tile (deterministic and cheap) and keeps the rays
        whose first instance box it owns, so no camera ray moves just to reach its first
        candidate; rays that enter no owned box start on the tile's shard, p.index % k."""
        rays = self.integrator.primary(p)
        if self.k == 1:
            return rays
        first = nearest_unvisited(self.world, self.owned, rays.origin, rays.direction,
                                  rays.tmax, np.zeros(len(rays), np.uint64))
        mine = (first == self.id) | ((first == DONE) & (p.index % self.k == self.id))
        return rays.take(mine)

    # -- the wavefront inside one call ---------------------------------------------

    def _state(self, item: WorkItem) -> _PassState:
        st = self.passes.get(item.token)
        if st is None:
            st = self.passes[item.token] = _PassState(item.token,
                                                      np.zeros((item.pass_.n_pixels, 3)))
        st.calls += 1
        return st

    def _run(self, call: _Call, rays: RayBatch, shadow: ShadowRayBatch) -> list:
        """The wavefront: intersect locally, route (top level, proxies), shade what ends
        here, trace its shadow rays; repeat until every ray has ended or left. Returns
        (k,) {token: Parcel} per target shard. With one shard this is the reference."""
        stats = call.stats
        out_rays = [[] for _ in range(self.k)]
        out_shadow = [[] for _ in range(self.k)]
        while len(rays) or len(shadow):
            if len(rays):
                settled = (rays.flags & FLAG_SHADE) != 0
                arrived, rays = rays.take(settled), rays.take(~settled)
                stats.bind(call.tok(rays.pixel)).count_rays(rays.kind)
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
                stats.bind(call.tok(done.pixel)).count_hops(done.hops)
                with stats.phase("shade"):
                    shaded = self.integrator.shade(done)
                call.splat(shaded.pixel, shaded.rgb)
                shadow = ShadowRayBatch.concat([shadow, shaded.shadow])
                rays = shaded.secondary
            if len(shadow):
                stats.bind(call.tok(shadow.pixel)).count_rays(np.full(len(shadow), SHADOW))
                shadow = shadow.replace(visited=shadow.visited | self.bit)
                with stats.phase("local_intersect"):
                    free = ~self.local.intersect_occluded(shadow.origin, shadow.direction,
                                                          shadow.tmax)
                stats.count_hops(shadow.hops, ~free)  # occluded here: these rays finish too
                shadow = shadow.take(free)
                with stats.phase("top_level"):
                    shadow, target = self.policy.route_shadow(
                        shadow, stats.bind(call.tok(shadow.pixel)))
                self._send(shadow, target, out_shadow)
                done = shadow.take(target == DONE)
                stats.bind(call.tok(done.pixel)).count_hops(done.hops)
                call.splat(done.pixel, done.contribution.astype(np.float64))
                shadow = ShadowRayBatch.empty()
        out = []
        for t in range(self.k):
            moving = (RayBatch.concat(out_rays[t]), ShadowRayBatch.concat(out_shadow[t]))
            by_token = {}
            for i, (r, sh) in enumerate(zip(*(call.split(b) for b in moving), strict=True)):
                if len(r) + len(sh):
                    st = call.states[i].stats
                    for kind, batch in (("rays", r), ("shadow", sh)):
                        if len(batch):
                            self._count_transfer(st, kind, batch)
                    by_token[call.tokens[i]] = Parcel(r, sh)
            out.append(by_token)
        stats.finish()
        return out

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
