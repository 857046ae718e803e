"""The Shard: one slice of the scene's geometry in Embree, the replicated instance table
and lights, and the traversal policy. A plain class that knows nothing of Ray: the
single-process reference drives it in process, and `nprt.workers.runtime.remote.ShardActor`
drives it inside a Ray actor (mailbox, direct sends), so the driver never imports it.

`step` is the unit of work: whatever has arrived (rays of any pass, from any sender, and
orders to generate the camera rays of passes) runs as one wavefront as far as it goes
here, and comes out as one parcel per target shard at its end; a caller that asks for it
(`emit`) gets parcels during the step as well, once enough rays are leaving for a shard,
so that the other shards need not wait for the step's end (see `Shard.step`). Film contributions and
statistics are kept per pass until `collect`; a pass's contributions are summed as exact
integers (nprt.workers.filmsum), so its film depends neither on how its rays were grouped
into steps (timing) nor on how they were split over shards: any run, faulted or not, at
any K, gives the same bytes.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from nprt.scene.model import Mesh
from nprt.workers.filmsum import MAX_EXP, FilmSums
from nprt.workers.jitcache import cold_modules_run_by
from nprt.workers.kernels import tiles
from nprt.workers.kernels.buckets import group_rows, mark_for_owner
from nprt.workers.kernels.filmsum import splat
from nprt.workers.passes import Pass, count_tiles, pass_at, tile_of
from nprt.workers.routing.exact import DONE, nearest_unvisited, visited_bit
from nprt.workers.routing.policies import ExactPolicy, OraclePolicy, ProxyPolicy
from nprt.workers.runtime.protocol import (
    EVERYWHERE,
    MeshRequest,
    Parcel,
    ShardConfig,
    sum_credits,
)
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats, SplitStats
from nprt.workers.traversal.closest import resolve_closest, resolve_closest_routed
from nprt.workers.traversal.geometry import MeshGeometry
from nprt.workers.traversal.local import LocalGeometry
from nprt.workers.wavefront.batch import (
    FLAG_SHADE,
    ORIGIN_DTYPE,
    PRIMARY,
    SHADOW,
    RayBatch,
    ShadowRayBatch,
)
from nprt.workers.wavefront.filmpool import FilmPool
from nprt.workers.wavefront.integrator import PathIntegrator
from nprt.workers.wavefront.world import ShardWorld

log = logging.getLogger(__name__)


@dataclass
class _PassState:
    """One pass's share of the film here, added up as its contributions arrive (`_Step.splat`)
    as exact integers (nprt.workers.filmsum) in its slot of the shard's FilmPool: the same
    for any order of the contributions and any split of them over steps and shards. A
    finished pass is collected whole, so no step writes it while `collect` reads it."""

    pass_: Pass
    slot: tuple[int, int]  # its film in the shard's FilmPool (index, generation)
    stats: RenderStats = field(default_factory=RenderStats)
    # Rare: contributions the words cannot hold (not finite, or beyond 2^MAX_EXP), kept as
    # (index (k,) int64 within the tile, rgb (k, 3) float64) to be summed at `collect`.
    outside: list = field(default_factory=list)

    def sums(self, films: FilmPool) -> FilmSums:
        """This shard's share of the pass's film (its slot is freed), its float sums of the
        contributions outside the words in a canonical order."""
        n = self.pass_.n_pixels
        out = films.release(self.slot, n)
        if self.outside:
            i = np.concatenate([idx for idx, _ in self.outside])
            rgb = np.concatenate([rgb for _, rgb in self.outside])
            v = np.where(np.abs(rgb) < 2.0 ** MAX_EXP, 0.0, rgb)
            order = np.lexsort((v[:, 2], v[:, 1], v[:, 0], i))
            out.rest = np.stack([np.bincount(i[order], weights=v[order, c], minlength=n)
                                 for c in range(3)], axis=1)
        return out


@dataclass
class StepResult:
    """parcels: (k,) Parcel or None per target shard (epoch and source left to the
    caller); returned: pass index -> weight of the rays that ended here; times: the
    step's phase times (wall and CPU); carried: rays (and shadow rays) this shard keeps
    for its next step (`Shard.step`, carry), with their share of the weight."""

    parcels: list
    returned: dict[int, Fraction]
    times: RenderStats
    rays_in: int = 0
    bytes_in: int = 0
    carried: int = 0


TOKS_KEPT = 4  # pass tokens an iteration reuses: rays, shadow rays, the unoccluded, done


class _Step:
    """The passes of one step. A ray's pixel names its tile, and at most one pass per tile
    is live (the coordinator's rule), so `tok` finds each ray's pass without a column on
    the wire."""

    def __init__(self, s: RenderSettings, states: list[_PassState], lookup: np.ndarray,
                 films: FilmPool):
        self.s, self.states, self.films = s, states, films
        self.lookup = lookup  # (tiles,) int64 -> index into states, -1: none in this step
        self._toks: list = []  # (pixel column, tok) of the last columns tok was asked for
        self.stats = SplitStats([st.stats for st in states])
        # (tiles,) int64 -> the film slot of the tile's pass (-1: none in this step), so one
        # pass over a batch adds each row to its pass's film, whatever the passes
        slots = np.array([st.slot[0] for st in states] + [-1], np.int64)
        self.slot_of_tile = slots[lookup]
        # Set by `Shard.step`: the weight the step still holds (pass index -> Fraction), and
        # where parcels go before the step ends (`Shard._emit`; None: only at its end).
        self.credits: dict[int, Fraction] = {}
        self.emit = None
        self.emit_rays = 0
        self.carry = None  # `Shard.step`'s carry
        self.carried: tuple | None = None  # (rays, shadow rays) left for the next step
        self.out_camera: list = []  # per target: camera rays by name leaving (`_generate`)

    def tok(self, pixel: np.ndarray, of: np.ndarray | None = None, rows=None) -> np.ndarray:
        """pixel (n,) uint32 -> (n,) int64 index of its pass in this step. The last few
        answers are kept (an iteration asks about its rays, its shadow rays and their
        subsets): a batch whose rows all go on shares its pixel column (columns are never
        written). of, rows: pixel is of[rows] (rows an index array or bool mask), so where
        of's answer is kept, this one is that answer's rows: a take, not a lookup."""
        tok = self._kept(pixel)
        if tok is not None:
            return tok
        if len(self.states) == 1:
            tok = np.zeros(len(pixel), np.int64)
        elif of is not None and (known := self._kept(of)) is not None:
            tok = known[rows]
        else:
            tok = tiles.pass_slots(pixel, self.s.width, self.s.tile_size, self.lookup)
        self._toks = [(pixel, tok), *self._toks[:TOKS_KEPT - 1]]
        return tok

    def _kept(self, pixel: np.ndarray) -> np.ndarray | None:
        for of, tok in self._toks:
            if pixel is of:
                return tok
        return None

    def splat(self, pixel: np.ndarray, rgb: np.ndarray) -> None:
        """Add rgb (n, 3) float32 or float64 at pixel (n,) uint32 to each pass's film."""
        if len(pixel) == 0:
            return
        pixel = np.ascontiguousarray(pixel, np.uint32)
        rgb = np.ascontiguousarray(rgb)
        outside = np.zeros(len(pixel), bool)
        f = self.films
        if splat(pixel, rgb, self.s.width, self.s.tile_size, self.slot_of_tile, f.x0, f.y0,
                 f.tile_w, f.words, outside):  # rare: kept for `_PassState.sums`
            rows = np.flatnonzero(outside)
            tok = tiles.pass_slots(pixel[rows], self.s.width, self.s.tile_size, self.lookup)
            local = tiles.tile_index(pixel[rows], self.s.width, self.s.tile_size)
            for j, st in enumerate(self.states):
                mine = np.flatnonzero(tok == j)
                if len(mine):
                    st.outside.append((local[mine], np.asarray(rgb[rows[mine]], np.float64)))


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
        self.passes: dict[int, _PassState] = {}  # pass index -> its state, until collected
        # Rays, shadow rays and weight carried into the next step (`step`, carry), or None
        self.carried: tuple[RayBatch, ShadowRayBatch, dict[int, Fraction]] | None = None
        self.films: FilmPool | None = None  # the live passes' films (made for the tile size)
        # Proxy policy: a step's rays and shadow rays ask the proxies together
        # (`_wavefront_together`); False asks per ray kind, for tests to compare the two.
        self.ask_together = True
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
                "meshes": sorted(self.meshes), "load_s": round(self.load_s, 4),
                "cold_kernels": len(cold_modules_run_by(
                    True, proxies=self.config.settings.mode == "proxy"))}

    def warm(self) -> float:
        """Trace two 4x4-pixel, 1-sample passes and drop them, so every kernel is compiled
        (or loaded from numba's cache) before the first timed pass: one at the image's
        centre and one halfway to its bottom edge, where a view usually meets geometry (a
        corner tile often sees only sky, and then the shading kernels were compiled inside
        the first render). Returns seconds taken."""
        t0 = time.perf_counter()
        s = self.config.settings
        self.begin(s)
        passes = {}
        for y in (s.height // 2, (3 * s.height) // 4):
            # A 4x4 corner of the pass (chunk 0) whose tile holds pixel (width / 2, y): the
            # step keeps a pass's state by its index, so the block must lie in that tile.
            whole = pass_at(s, int(tile_of(s, np.uint32([y * s.width + s.width // 2]))[0]))
            w, h = min(4, whole.x1 - whole.x0), min(4, whole.y1 - whole.y0)
            x0 = min(max(s.width // 2 - w // 2, whole.x0), whole.x1 - w)
            y0 = min(max(y - h // 2, whole.y0), whole.y1 - h)
            passes[whole.index] = Pass(whole.index, x0, y0, x0 + w, y0 + h, whole.sample0,
                                       whole.sample0 + 1)
        self.step(list(passes.values()), [], {i: Fraction(1) for i in passes})
        self.reset()
        self._warm_occlusion()
        self.policy.warm()
        return time.perf_counter() - t0

    def _warm_occlusion(self) -> None:
        """One shadow query through the walk this shard's steps use: the warm-up tile may
        hit nothing and cast no shadow ray, and the occlusion walk was then compiled (or
        loaded from the cache) inside the first timed pass."""
        origin = np.zeros((1, 3), ORIGIN_DTYPE)
        direction = np.float32([[0.0, 0.0, 1.0]])
        tmax = np.full(1, np.inf, np.float32)
        fused = self._fused_routing()
        if fused is None:
            self.local.intersect_occluded(origin, direction, tmax)
        else:
            self.local.occluded_routed(origin, direction, tmax, fused, np.zeros(1, np.uint64))

    def _fused_routing(self) -> np.ndarray | None:
        """What the local walks route among (the exact policy's `cand_owner`) when they also
        find each ray's next stop (one walk of the top level a ray;
        nprt.workers.routing.exact.next_stop); None when they do not: alone, or another
        policy."""
        if not len(self.remote) or type(self.policy) is not ExactPolicy:
            return None
        return self.policy.cand_owner

    # -- a job ----------------------------------------------------------------------

    def begin(self, settings: RenderSettings) -> None:
        """Start a job (or a re-run after a fault): its settings, and no pass state."""
        self.configure(settings)
        self.reset()

    def reset(self) -> None:
        self.passes.clear()
        self.carried = None
        if self.films is not None:
            self.films.clear()

    @property
    def carried_rays(self) -> int:
        """Rays and shadow rays carried into the next step (`step`, carry)."""
        return 0 if self.carried is None else len(self.carried[0]) + len(self.carried[1])

    def collect(self, indices: list[int]) -> list[tuple]:
        """[(pass index, FilmSums of n_pixels or None, stats dict)] of finished
        passes (None: this shard never saw the pass); their state is dropped here."""
        out = []
        for i in indices:
            st = self.passes.pop(i, None)
            try:
                out.append((i, None, None) if st is None
                           else (i, st.sums(self.films), st.stats.to_dict()))
            except ValueError:  # its run was reset while this collect ran: nothing here
                out.append((i, None, None))
        return out

    # -- the wavefront ---------------------------------------------------------------

    def step(self, orders: list[Pass], parcels: list, credits: dict[int, Fraction],
             emit=None, emit_rays: int = 0, carry=None) -> StepResult:
        """Run the camera rays of `orders` and the rays of `parcels` (Parcel) as one
        wavefront, with the rays the last step carried. credits: pass index -> the weight
        that came with them. Returns the parcels for other shards (weights shared out) and
        the weight of passes whose rays all ended here.

        carry: None, or a callable given the rays (shadow rays included) still here after
        an iteration, from the second on, that says whether they wait for the next step
        (the runtime's rule: `remote.carry_when`). If so they are kept in `carried` with a
        share of their passes' weight, as if sent to this shard, and the step ends; the
        caller steps this shard again, and that step runs them with whatever else it
        takes. Not a transfer: no hop, no bytes. A ray's answer does not depend on its
        batch, nor the film on the order of its contributions: the same film.

        emit: None, or a callable given (k,) parcels (Parcel or None per target) that leave
        before the step ends: at the start of each iteration of the wavefront, what the
        camera rays and the iterations before sent on to each target that has emit_rays
        rays or more waiting (camera rays by name count). A step of 100,000 rays runs for
        a tenth of a second, and a peer with nothing else to do would wait all of it for
        the rays the first iteration sent it.
        Each such parcel carries a share of its passes' weight: a pass with rays for t
        targets gives each 1 / (t + 1) of what the step holds and keeps the rest, so the
        weight still adds up exactly (`_pack`)."""
        times = RenderStats()
        # "bookkeeping" is the batch glue between the named stages (take, concat, replace,
        # counters): every second of a step is in some phase.
        with times.phase("bookkeeping"):
            with times.phase("receive"):
                received = [p.rays for p in parcels if p.rays is not None]
                shadow = [p.shadow for p in parcels if p.shadow is not None]
                bytes_in = sum(p.nbytes for p in parcels)
                if parcels:
                    times.phase_s["transfer_wait"] += max(
                        0.0, time.time() - min(p.sent_at for p in parcels))
                n_carried = 0
                if self.carried is not None:  # not received: counted in no rays_in
                    kept_rays, kept_shadow, kept_credits = self.carried
                    self.carried = None
                    received.append(kept_rays)
                    shadow.append(kept_shadow)
                    credits = sum_credits([credits, kept_credits])
                    n_carried = len(kept_rays) + len(kept_shadow)
                step = self._open(sorted(credits), times)
            step.credits = dict(credits)  # the weight still held here (`_emit` gives some)
            step.emit, step.emit_rays = emit, emit_rays
            step.carry = carry
            out_rays, out_shadow = [], []  # (batch, rows, targets, tokens) leaving (`_send`)
            out_camera = step.out_camera = [[] for _ in range(self.k)]
            made = []  # the camera rays that start here
            with times.phase("generate"):
                if orders:
                    made.append(self._generate(orders, step, out_camera))
                for p in parcels:
                    if p.camera is not None:  # camera rays sent by name: made here
                        cam = self.integrator.camera_rays(*p.camera)
                        made.append(cam.replace(hops=np.ones(len(cam), np.uint8)))
            arrived, rays = _split_settled(received, made)
            n_in = len(arrived) + len(rays) + sum(len(b) for b in shadow) - n_carried
            self._wavefront(step, arrived, rays, shadow, out_rays, out_shadow)
            with times.phase("send"):
                parcels_out, returned = self._pack(step, out_rays, out_shadow, out_camera,
                                                   step.credits)
        step.stats.finish()  # after the bookkeeping phase closes: its time is shared too
        return StepResult(parcels_out, returned, times, n_in, bytes_in, self.carried_rays)

    def _open(self, indices: list[int], times: RenderStats) -> _Step:
        """The step over these passes: their state (made on first sight) and the tile
        lookup that finds a ray's pass."""
        n = self.s.tile_size ** 2
        if self.films is None or self.films.n != n:
            if self.passes:
                raise RuntimeError(f"{self!r}: tile size changed with passes in flight")
            self.films = FilmPool(n)
        states = []
        for i in indices:
            st = self.passes.get(i)
            if st is None:
                p = pass_at(self.s, i)
                st = self.passes[i] = _PassState(p, self.films.take(p))
            states.append(st)
        tiles = count_tiles(self.s)
        lookup = np.full(tiles, -1, np.int64)
        for j, i in enumerate(indices):
            lookup[i % tiles] = j
        step = _Step(self.s, states, lookup, self.films)
        step.stats.times = times  # the step's phases are timed in `times`
        return step

    def _generate(self, orders: list[Pass], step: _Step, out_camera: list) -> RayBatch:
        """The camera rays of each ordered pass, generated here once. Rays whose first
        instance box is another shard's go there by name ((pixel, sample) into
        out_camera, per target); the rest (first box here, or none) start here and are
        returned."""
        # The passes' names joined (8 bytes a ray), then one batch made of them: the same
        # rows as each pass's `primary` concatenated, without copying every column again.
        pixel, sample = [], []
        for p in orders:
            pix, smp = self.integrator.camera_names(p)
            st = step.states[step.lookup[p.index % len(step.lookup)]]
            st.stats.counters["camera_rays_generated"] += len(pix)
            pixel.append(pix)
            sample.append(smp)
        rays = self.integrator.camera_rays(np.concatenate(pixel), np.concatenate(sample))
        if self.k == 1 or len(rays) == 0:
            return rays
        first = nearest_unvisited(self.world, self.owned, rays.origin, rays.direction,
                                  rays.tmax, np.zeros(len(rays), np.uint64))
        here = (first == self.id) | (first == DONE)
        away = np.flatnonzero(~here)
        for dest in np.unique(first[away]):
            rows = away[first[away] == dest]
            out_camera[int(dest)].append((rays.pixel[rows], rays.sample[rows]))
        return rays.take(here)

    def _wavefront(self, step: _Step, arrived: RayBatch, rays: RayBatch, shadow: list,
                   out_rays: list, out_shadow: list) -> None:
        """Intersect locally, route (top level, proxies), shade what ends here, trace its
        shadow rays; repeat until every ray has ended or left. arrived: rays sent here only
        to be shaded (`_split_settled`); shadow: the shadow batches received. Rays leaving
        go into out_rays / out_shadow (`_send`). With one shard this is the reference."""
        if self.ask_together and len(self.remote) and isinstance(self.policy, ProxyPolicy):
            return self._wavefront_together(step, arrived, rays, ShadowRayBatch.concat(shadow),
                                            out_rays, out_shadow)
        stats = step.stats
        # Every instance is here and no ray can come from elsewhere (the reference, or any
        # policy at K = 1): every ray ends here, so routing and visited bits are skipped.
        # Proxy mode at K = 1 spent up to 14 % more CPU than exact without this. With other
        # shards, a proxy policy still checks the rays their proxies sent here (the
        # misprediction counts).
        alone = not len(self.remote) and (self.k == 1 or type(self.policy) is ExactPolicy)
        fused = self._fused_routing()
        waiting = shadow  # shadow batches to trace, joined once (received ones too)
        first = True
        while len(arrived) or len(rays) or any(len(b) for b in waiting):
            if not first and self._carries(step, len(rays) + sum(len(b) for b in waiting)):
                step.carried = (rays, ShadowRayBatch.concat(waiting))
                return
            first = False
            self._emit(step, out_rays, out_shadow)  # what the last iteration sent on
            if len(arrived) or len(rays):
                rays, near = self._intersect(step, rays, alone, fused)
                done = None  # every row of rays ends here
                if not alone:
                    with stats.phase("top_level"):
                        if near is None:
                            rays, target = self.policy.route_rays(rays, stats)
                        else:
                            rays, target = self.policy.route_rays(rays, stats, near)
                    rays, done = self._leave(step, rays, target, out_rays)
                shaded = self._shade(step, arrived, rays, done)
                arrived = RayBatch.empty()
                waiting = [*waiting, shaded.shadow]
                rays = shaded.secondary
            shadow, waiting = ShadowRayBatch.concat(waiting), []
            if len(shadow):
                free, near = self._occlude(step, shadow, fused)
                if not len(self.remote):  # nothing elsewhere: every shadow ray ends here
                    stats.count_hops(shadow.hops)
                    lit = np.flatnonzero(free)  # a take: a bool index of (n, 3) is ~6x slower
                    step.splat(shadow.pixel[lit], np.take(shadow.contribution, lit, axis=0))
                    continue
                if near is not None and type(self.policy) is ExactPolicy:
                    self._route_shadow_all(step, shadow, free, near, out_shadow)
                    continue
                shadow = self._unoccluded(step, shadow, free)
                with stats.phase("top_level"):
                    if near is None:
                        shadow, target = self.policy.route_shadow(
                            shadow, stats.bind(step.tok(shadow.pixel)))
                    else:
                        shadow, target = self.policy.route_shadow(
                            shadow, stats.bind(step.tok(shadow.pixel)), near.take(free))
                self._end_shadow(step, shadow, target, out_shadow)

    def _wavefront_together(self, step: _Step, arrived: RayBatch, rays: RayBatch,
                            shadow: ShadowRayBatch, out_rays: list, out_shadow: list) -> None:
        """`_wavefront` for the proxy policy with other shards: each iteration routes its
        rays and the shadow rays of the previous one's shading with one `predict` (one call
        of each mesh's nets, which cost about 45 us each whatever their rows, not one per
        ray kind). Each ray meets the same tests as in `_wavefront`, and a net's answer for
        a row does not depend on its batch (`Proxy.run`), nor the film on the order of its
        contributions (`_PassState`): the same film and counts."""
        stats = step.stats
        first = True
        while len(arrived) or len(rays) or len(shadow):
            if not first and self._carries(step, len(rays) + len(shadow)):
                step.carried = (rays, shadow)
                return
            first = False
            self._emit(step, out_rays, out_shadow)  # what the last iteration sent on
            given = len(arrived) + len(rays) > 0
            if given:
                rays, _ = self._intersect(step, rays, False, None)
            if len(shadow):
                free, _ = self._occlude(step, shadow, None)
                shadow = self._unoccluded(step, shadow, free)
            with stats.phase("top_level"):
                routed_rays, (shadow, target) = self.policy.route_together(
                    rays if given else None, step.tok(rays.pixel), shadow,
                    step.tok(shadow.pixel), stats)
            self._end_shadow(step, shadow, target, out_shadow)
            shadow = ShadowRayBatch.empty()
            if given:
                shaded = self._shade(step, arrived, *self._leave(step, *routed_rays, out_rays))
                arrived = RayBatch.empty()
                shadow, rays = shaded.shadow, shaded.secondary

    @staticmethod
    def _carries(step: _Step, left: int) -> bool:
        """Whether the `left` rays still here go to the next step (`step`, carry)."""
        return step.carry is not None and bool(step.carry(left))

    def _intersect(self, step: _Step, rays: RayBatch, alone: bool, fused):
        """Count rays and intersect them here. Returns (rays, intersected; the routing
        walk's answer for them, or None)."""
        stats = step.stats
        stats.bind(step.tok(rays.pixel)).count_rays(rays.kind)
        if not alone:
            rays = rays.replace(visited=rays.visited | self.bit)
        near = None
        with stats.phase("local_intersect"):
            if fused is None:
                rays = resolve_closest(rays, self.local, self.world.lights)
            else:
                rays, near = resolve_closest_routed(rays, self.local, self.world.lights, fused)
        return rays, near

    def _shade(self, step: _Step, arrived: RayBatch, rays: RayBatch, done):
        """Shade the rays ending here (arrived to be shaded, then the rows done (index array,
        or None: all) of rays) and add what they bring to the film; returns the
        integrator's answer (secondary and shadow rays)."""
        stats = step.stats
        rows, done = done, RayBatch.gather([(arrived, None), (rays, done)])
        tok = step.tok(done.pixel) if len(arrived) else step.tok(done.pixel, rays.pixel, rows)
        stats.bind(tok).count_hops(done.hops)
        with stats.phase("shade"):
            shaded = self.integrator.shade(done)
        step.splat(shaded.pixel, shaded.rgb)
        return shaded

    def _occlude(self, step: _Step, shadow: ShadowRayBatch, fused):
        """Count shadow rays and test them against the geometry here: (n,) bool free, and
        the routing walk's answer (None unless fused)."""
        step.stats.bind(step.tok(shadow.pixel)).count_rays(SHADOW)
        near = None
        with step.stats.phase("local_intersect"):
            if fused is None:
                free = ~self.local.intersect_occluded(shadow.origin, shadow.direction,
                                                      shadow.tmax)
            else:
                occluded, near = self.local.occluded_routed(
                    shadow.origin, shadow.direction, shadow.tmax, fused, shadow.visited)
                free = ~occluded
        return free, near

    def _unoccluded(self, step: _Step, shadow: ShadowRayBatch, free: np.ndarray):
        """The shadow rays not occluded here, with this shard visited; the others finish."""
        step.stats.count_hops(shadow.hops, ~free)  # occluded here: these rays finish too
        kept = shadow.take(free)
        step.tok(kept.pixel, shadow.pixel, free)  # kept for the routing's question
        return kept.replace(visited=kept.visited | self.bit)

    def _route_shadow_all(self, step: _Step, shadow: ShadowRayBatch, free: np.ndarray,
                          near, out_shadow: list) -> None:
        """`_unoccluded`, then routing and `_end_shadow`, for exact forwarding with the
        routing walk's answer: every row is routed (the answer is meaningless for the
        occluded ones, which then finish here), so the unoccluded rows are not copied out
        first. The same targets: `next_stop` is per row, and the walk's tmax is the rays'
        own, so no row is asked again (`nprt.workers.routing.exact._routed`). The visited
        bit goes on as the rows leave (`_by_target`)."""
        step.stats.count_hops(shadow.hops, ~free)  # occluded here: these rays finish too
        with step.stats.phase("top_level"):
            _, target = self.policy.route_shadow(shadow, step.stats.bind(step.tok(shadow.pixel)),
                                                 near)
        self._end_shadow(step, shadow, np.where(free, target, DONE), out_shadow, free)

    def _end_shadow(self, step: _Step, shadow: ShadowRayBatch, target: np.ndarray,
                    out_shadow: list, free: np.ndarray | None = None) -> None:
        """Send routed shadow rays on; those done here add their contribution (free: (n,)
        bool, the rows not occluded, where occluded ones are among the DONE targets)."""
        done = self._send(step, shadow, target, out_shadow)
        if free is not None:
            done = done[free[done]]
        pixel, hops, rgb = shadow.pixel, shadow.hops, shadow.contribution
        if len(done) < len(shadow):  # only the columns a finished shadow ray still needs
            pixel, hops, rgb = pixel[done], hops[done], np.take(rgb, done, axis=0)
        step.stats.bind(step.tok(pixel, shadow.pixel, done)).count_hops(hops)
        step.splat(pixel, rgb.astype(np.float64))

    def _leave(self, step: _Step, rays: RayBatch, target: np.ndarray, out_rays: list
               ) -> tuple:
        """Send routed rays on (into out_rays); returns (rays, flagged; the rows of those
        that end here, (r,) int64 or None: all)."""
        # Rays going to their hit's owner only to be shaded are not re-intersected:
        # a second Embree call with tmax == t may pick a different triangle on an edge.
        flags, marked = mark_for_owner(rays.flags, np.ascontiguousarray(target, np.int32),
                                       rays.hit_inst, self.world.owner, np.uint8(FLAG_SHADE))
        if marked:
            rays = rays.replace(flags=flags)
        done = self._send(step, rays, target, out_rays)
        return rays, (None if len(done) == len(rays) else done)

    def _emit(self, step: _Step, out_rays: list, out_shadow: list) -> None:
        """Hand `step.emit` the parcels for the targets whose rows leaving so far add up
        to `step.emit_rays` or more (camera rays by name count), with their shares of the
        weight (`_pack`, keep); those rows leave the lists, the others stay for later.
        Per target, not in all: a parcel costs a Ray call whatever it holds, and at large
        K, where a step's rows are spread over many targets, the shards are kept busy by
        one another anyway (bench/README.md, "The wall on K dedicated cores, simulated").
        No-op without `emit`."""
        if step.emit is None:
            return
        cams = step.out_camera
        count = np.zeros(self.k, np.int64)
        for _, _, targets, _ in (*out_rays, *out_shadow):
            count += np.bincount(targets, minlength=self.k)
        for t, sent in enumerate(cams):
            count[t] += sum(len(c[0]) for c in sent)
        chosen = count >= max(step.emit_rays, 1)
        if not chosen.any():
            return
        with step.stats.phase("send"):
            go_rays, go_shadow = _split_out(out_rays, chosen), _split_out(out_shadow, chosen)
            go_cams = [sent if chosen[t] else [] for t, sent in enumerate(cams)]
            for t in np.flatnonzero(chosen).tolist():
                cams[t] = []  # in place: the step's out_camera stays the one list
            parcels, _ = self._pack(step, go_rays, go_shadow, go_cams, step.credits, keep=True)
            step.emit(parcels)

    def _pack(self, step: _Step, out_rays: list, out_shadow: list, out_camera: list,
              credits: dict[int, Fraction], keep: bool = False) -> tuple[list, dict]:
        """One parcel per target holding every pass's rays for it. A pass's weight is
        shared equally by the parcels that carry its rays; a pass with no ray leaving
        returns its whole weight. keep (a parcel sent before the step ends, `_emit`): the
        step keeps an equal share too, credits is updated to what it keeps, and no weight
        is returned. The step's carried rays (`step.carried`, set when its wavefront stops:
        never during an `_emit`) count as one more target of their passes; their share goes
        into `self.carried`."""
        npass = len(step.states)
        seen = np.zeros((self.k, npass), bool)  # target, pass: the pass has rays for it
        held = np.zeros(npass, bool)  # the pass has carried rays
        carried = step.carried
        if carried is not None:
            for batch in carried:
                held[step.tok(batch.pixel)] = True
        rays = self._by_target(RayBatch, step, out_rays, seen, None)
        shadow = self._by_target(ShadowRayBatch, step, out_shadow, seen, SHADOW)
        cams: list = [None] * self.k
        for t, sent in enumerate(out_camera):
            if sent:
                cam = cams[t] = tuple(np.concatenate(c) for c in zip(*sent, strict=True))
                tok = step.tok(cam[0])
                seen[t, tok] = True
                step.stats.bind(tok)  # by name: primary transfers of 8 bytes
                step.stats.count_transfers(PRIMARY, sum(a.itemsize for a in cam))
                step.stats.count("camera_rays_sent_by_name")
        parcels: list = [None] * self.k
        returned = {}
        shares: list[dict] = [{} for _ in range(self.k)]
        kept: dict[int, Fraction] = {}  # the carried rays' weight
        by_pass = [[] for _ in step.states]  # per pass: the targets its rays go to
        for j, t in zip(*(a.tolist() for a in np.nonzero(seen.T)), strict=True):
            by_pass[j].append(t)
        for st, targets, hold in zip(step.states, by_pass, held.tolist(), strict=True):
            i, w = st.pass_.index, credits[st.pass_.index]
            if not targets and not hold:
                if not keep:
                    returned[i] = w
                continue
            part = w / (len(targets) + int(keep) + int(hold))
            if keep:
                credits[i] = part
            if hold:
                kept[i] = part
            for t in targets:
                shares[t][i] = part
        if carried is not None:
            self.carried = (*carried, kept)
        for t in range(self.k):
            if shares[t]:
                parcels[t] = Parcel(-1, shares[t], rays[t], shadow[t], camera=cams[t])
        return parcels, returned

    def _by_target(self, cls, step: _Step, pending: list, seen: np.ndarray, kind) -> list:
        """The rows leaving in pending [(batch, rows (m,) int64, targets (m,) int32 sorted,
        their pass tokens (m,) int64)] (`_send`) as (k,) batches or None per target shard,
        one hop more, each target's rows in the order they were sent (rays to be shaded
        there first, FLAG_SHADE). All of a step's rows for other shards are gathered once
        per column (not the whole batches they leave from: at K = 2 half their rows stay),
        taken again only where they must be reordered, and each target's batch is a view
        of that (small parts made a take per part and a concat per target cost a numpy call
        per column each). Counts their transfers and marks seen[target, pass]; kind: the
        ray kind of a shadow batch (None: the batch's kind column)."""
        if not pending:
            return [None] * self.k
        if len(pending) == 1:
            batch, rows, targets, tok = pending[0]
        else:  # the leaving rows alone, copied once, then grouped by target (stable)
            batch = cls.gather([(b, r) for b, r, _, _ in pending])
            targets = np.concatenate([x for _, _, x, _ in pending])
            tok = np.concatenate([x for _, _, _, x in pending])
            rows = None  # every row of batch, in order
            if (targets[1:] < targets[:-1]).any():  # else grouped already (one target: K = 2)
                rows, _ = group_rows(targets, self.k)
                targets, tok = targets[rows], tok[rows]
        if kind is None:  # a target's rays to be shaded there first: `_split_settled` slices
            flags = batch.flags if rows is None else np.take(batch.flags, rows)
            settled = (flags & FLAG_SHADE) != 0
            if settled.any():
                order, _ = group_rows((targets * 2 + ~settled).astype(np.int32), 2 * self.k)
                rows = order if rows is None else rows[order]
                targets, tok = targets[order], tok[order]
        moving = batch if rows is None else batch.take(rows)
        if kind is None:
            moving = moving.replace(hops=moving.hops + np.uint8(1))
        else:  # shadow rays carry this shard's visited bit from here on (`_route_shadow_all`)
            moving = moving.replace(hops=moving.hops + np.uint8(1),
                                    visited=moving.visited | self.bit)
        seen[targets, tok] = True
        step.stats.bind(tok).count_transfers(moving.kind if kind is None else kind,
                                             moving._ROW_BYTES)
        bounds = np.searchsorted(targets, np.arange(self.k + 1)).tolist()
        return [moving.rows(a, b) if b > a else None
                for a, b in zip(bounds[:-1], bounds[1:], strict=True)]

    def _send(self, step: _Step, batch, target: np.ndarray, out: list) -> np.ndarray:
        """Note the rows of batch leaving for another shard, grouped by target, into out
        as (batch, rows (m,) int64, targets (m,) int32, pass tokens (m,) int64), gathered
        in `_pack`. Returns the rows (r,) int64 that end here (target DONE), in order."""
        order, starts = group_rows(np.ascontiguousarray(target, np.int32), self.k)
        if starts[1] < len(order):
            away = order[starts[1]:]
            out.append((batch, away, target[away].astype(np.int32),
                        step.tok(batch.pixel)[away]))
        return order[:starts[1]]


def _split_out(out: list, chosen: np.ndarray) -> list:
    """The entries of out [(batch, rows, targets, tokens)] (`Shard._send`) for the targets
    chosen ((k,) bool), returned; out keeps the rest, in place."""
    go, stay = [], []
    for batch, rows, targets, tok in out:
        sel = chosen[targets]
        if sel.all():
            go.append((batch, rows, targets, tok))
        elif sel.any():
            go.append((batch, rows[sel], targets[sel], tok[sel]))
            stay.append((batch, rows[~sel], targets[~sel], tok[~sel]))
        else:
            stay.append((batch, rows, targets, tok))
    out[:] = stay
    return go


def _split_settled(received: list, made: list) -> tuple[RayBatch, RayBatch]:
    """(the rays sent here only to be shaded (FLAG_SHADE: their hit is final), the flag
    cleared; every other ray) of the received batches, then the made ones, in order. A
    parcel holds its rays to be shaded first (`Shard._by_target`), so each part is a slice
    and the two batches are joined without a gather (any other order is taken apart)."""
    settled, rest = [], []
    for b in received:
        flagged = (b.flags & FLAG_SHADE) != 0
        s = int(np.count_nonzero(flagged))
        if s == 0:
            rest.append(b)
        elif flagged[:s].all():
            settled.append(b.rows(0, s))
            rest.append(b.rows(s, len(b)))
        else:
            settled.append(b.take(flagged))
            rest.append(b.take(~flagged))
    arrived = RayBatch.concat(settled)
    if len(arrived):
        arrived = arrived.replace(flags=arrived.flags & np.uint8(~FLAG_SHADE & 0xFF))
    return arrived, RayBatch.concat(rest + made)
