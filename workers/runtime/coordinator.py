"""The Coordinator: admits one job's passes to a pool of K Shard actors, learns when each
pass is complete, collects and sums its films, and re-runs passes after a shard dies. It
is not on the ray path: shards send parcels to each other directly
(`nprt.workers.runtime.remote.ShardActor`), and the coordinator never reads a ray batch.

Design:
- Camera rays once: a pass is ordered from one shard, `pass.index % K` (a fixed choice,
  so a re-run lands where the first run did and the film sums come out the same), which
  generates its camera rays and sends each to the owner of its first instance box.
- Completion by weight throwing: a pass starts with weight 1 (an exact Fraction), which
  travels with its rays; a shard that sends a pass's rays on shares the weight it got
  equally among those parcels, and hands back the weight of a pass none of whose rays
  left. The pass is done exactly when the coordinator has weight 1 back: nothing is
  counted, no message is ordered, and no shard waits for an acknowledgement.
- Pipelining: up to `window` passes are live, at most one per tile (a ray's pixel then
  names its pass on every shard, without a column on the wire). Shards merge whatever has
  arrived into one wavefront, so steps grow with load instead of calls with K; a long step
  sends what is leaving as it goes (`remote.EMIT_RAYS`), so its peers need not wait for
  its end.
- Films are collected from every shard once a pass is done as exact integers
  (nprt.workers.filmsum), summed, converted once and handed on (so exact mode equals the
  reference bit for bit at any K); `nprt.workers.render` adds them to the image per tile
  in pass order, so the bytes of an image never depend on timing. From K = 8
  (`COLLECT_ON_POLL_FROM_K`) a shard's films ride on its next long poll: one call instead
  of a poll and a collect per shard and finished pass, and finished passes batch while
  they wait. That wait (until the shard next hands back weight, at most POLL_S) keeps the
  pass's tile and window slot a little longer, so at the tail, with fewer than K passes
  still out, films are collected at once. On 2 cores at K = 8 it took 20-32 % off the
  coordinator's CPU, and the wall fell in 9 of 12 paired rounds (bench/README.md "Films
  ride on polls"). Rejected: a separate collect batched over several passes (the
  window's slots and tiles wait on it just the same, and it is still a call per shard).
- Failure: a shard that dies (a failed call) or restarted unseen (a new incarnation in a
  poll or collect reply) may have lost rays, weight or film of any live pass. Every live
  pass is re-run in a new epoch; parcels of the old epoch are dropped where they arrive.
  Weight lost without a fault (every shard idle for STALL_S while a pass waits) is handled
  the same way, so a job never waits for ever; a pass re-run MAX_PASS_ATTEMPTS times
  fails the job.

Rejected alternatives: the coordinator routing every parcel (the earlier design: two
hops and a decision per parcel, calls growing much faster than K); counting parcels sent
and received per pass instead of weights (reports race: a receiver's "consumed" can
reach the coordinator before the sender's "produced", so zero outstanding does not mean
done without an extra acknowledgement per hop); a barrier per wavefront bounce (idle
shards at every bounce's tail).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
import ray
from ray.exceptions import ActorUnavailableError, RayActorError

from nprt.scene.meta import SceneMeta
from nprt.scene.model import Scene
from nprt.workers.filmsum import FilmSums
from nprt.workers.passes import Pass, count_tiles
from nprt.workers.runtime import remote
from nprt.workers.runtime.calltrace import StepTrace
from nprt.workers.runtime.pool import (  # noqa: F401 (ShardStartError re-exported)
    PoolRegistry,
    ShardPool,
    ShardsLost,
    ShardStartError,
)
from nprt.workers.runtime.protocol import Parcel, PollReply
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats

log = logging.getLogger(__name__)

MAX_PASS_ATTEMPTS = 4
# Live passes per shard. More passes in flight make each step bigger (its fixed costs shared
# by more rays) and leave a shard idle less often waiting for its peers' parcels. At 3,
# shards of a 16-core machine were idle a third of the time at K = 2. At 6 (until session
# 11), on 2 cores at 640x360, K = 2 shards were busy 0.66-0.79 of the wall; at 24 (48 live)
# 0.79-0.94, with 10-15 % less CPU at K = 2 and 4 (bench/README.md, "A wider window"). A
# live pass holds a film slot on each shard it visits: tile_size^2 x 48 bytes, 192 KiB at
# 64-pixel tiles; and its paths' rays, about 330 bytes a path in flight: 24 passes of
# 64-pixel, 16-sample tiles are about 0.5 GB a shard (bench/README.md, "Bigger passes").
WINDOW_PER_SHARD = 24
MIN_WINDOW = 4
POLL_S = 0.25  # a shard's long poll; also how often a cancel is noticed
# From this K up, a finished pass's films ride on each shard's next poll (one call, not a
# poll and a collect) while at least K passes still wait for weight; past that (the job's
# tail), and below this K, they are collected at once. The saving grows with K (K - 1 calls
# a finished pass); the wait costs what it costs at any K. On 2 cores: walls shorter at
# K = 8 (9 of 12 paired rounds), mixed at K = 4 (exact longer in 3 of 6, proxy shorter in
# 5 of 6), exact longer at K = 2 (6 of 6) (bench/README.md "Films ride on polls").
COLLECT_ON_POLL_FROM_K = 8
BEGIN_TIMEOUT_S = 60.0  # every shard answering `begin` (a restarted one included)
BEGIN_RETRY_S = 0.5
SHARD_LOST = (RayActorError, ActorUnavailableError)
# Every shard idle (no step running, nothing in its inbox) this long while a pass still
# waits for weight: the weight can never come back (a lost parcel or a bug), and without
# this the job would wait for ever. Parcels in flight reach their shard in milliseconds.
STALL_S = 20.0


def live_window(k: int, tiles: int) -> int:
    """Passes live at once for K shards on an image of `tiles` tiles: WINDOW_PER_SHARD a
    shard, at least MIN_WINDOW, and never more than one a tile (the admission rule)."""
    return max(1, min(tiles, max(MIN_WINDOW, WINDOW_PER_SHARD * k)))


class _Restarted(RuntimeError):
    """A shard answered with a new incarnation: Ray restarted it, and its state is gone."""


class _Stalled(RuntimeError):
    """Every shard has been idle for STALL_S while passes wait for weight."""


class StallWatch:
    """Notices weight that went missing: how long each shard has answered its polls idle
    (no step running, nothing in its inbox, no weight handed back, no step or parcel since
    its first idle answer), measured on the shard's own clock, so a coordinator that was
    busy elsewhere and reads old answers late does not take them for a long silence."""

    def __init__(self, k: int):
        self.first: list[PollReply | None] = [None] * k  # first answer of the idle run
        self.idle_s = [0.0] * k

    def seen(self, reply: PollReply) -> None:
        s, first = reply.shard, self.first[reply.shard]
        quiet = reply.idle and not reply.returned
        if quiet and first is not None and (reply.steps, reply.parcels_in) == (
                first.steps, first.parcels_in):
            self.idle_s[s] = reply.at - first.at  # still the same idle run
        else:
            self.first[s] = reply if quiet else None
            self.idle_s[s] = 0.0

    def stalled(self, waiting_for_weight: bool) -> bool:
        return waiting_for_weight and min(self.idle_s) > STALL_S


@dataclass
class _Live:
    """A pass in flight: the weight back so far, and the shards' films once collected."""

    pass_: Pass
    weight: Fraction = field(default_factory=Fraction)
    parts: dict = field(default_factory=dict)  # shard -> (sums or None, stats dict or None)
    collecting: bool = False


class Coordinator:
    """One job on a pool of shards: a warm one from `pools`, or else a private one that it
    closes with itself. scene: a stored scene's SceneMeta (nprt.scene.store.open_scene; the
    driver then holds no geometry) or an in-memory Scene. on_progress: per-mesh proxy
    training progress while a new pool starts (ShardPool). trace: keep every shard step
    (bench/network/netmodel.py replays them)."""

    def __init__(self, scene: Scene | SceneMeta, settings: RenderSettings,
                 ray_address: str | None = None, proxy_dir=None,
                 shard_options: list[dict] | None = None, pools: PoolRegistry | None = None,
                 trace: bool = False, on_progress=None):
        self.scene, self.s, self.k = scene, settings, settings.shards
        self.trace = StepTrace(self.k) if trace else None
        self._pools, self._closed = pools, False
        if pools is not None:  # a warm pool, handed back on close
            self.pool = pools.acquire(scene, settings, ray_address=ray_address,
                                      proxy_dir=proxy_dir, shard_options=shard_options,
                                      on_progress=on_progress)
        else:
            self.pool = ShardPool(scene, settings, ray_address, proxy_dir, shard_options,
                                  on_progress)
        if (self.pool.k, self.pool.mode) != (self.k, settings.mode):
            raise ValueError(f"{self.pool!r} cannot run a K={self.k} {settings.mode!r} job")
        self.pool.jobs += 1
        self.pool.show(scene)  # a warm pool may still show another frame of its scene
        self.warm = self.pool.jobs > 1  # the pool was started for an earlier job
        self.window = live_window(self.k, count_tiles(settings))
        self.totals: list[PollReply | None] = [None] * self.k  # shards' totals, last run
        self._done_totals = [dict() for _ in range(self.k)]  # summed over earlier runs
        self.wall_s = self.wait_s = self.cpu_s = 0.0
        self.reruns = 0
        self._epochs = itertools.count(int(time.time() * 1e3) << 16)

    def set_frame(self, scene: Scene) -> None:
        """Render `scene`, a frame of this job's scene, from the next pass on: the shards
        swap their instance table and lights and keep their geometry and proxies."""
        self.scene = scene
        self.pool.show(scene)

    @property
    def actors(self):
        return self.pool.actors

    @property
    def shard_info(self) -> list[dict]:
        return self.pool.shard_info

    @property
    def partition(self):
        return self.pool.partition

    @property
    def plan(self):
        return self.pool.plan

    @property
    def prepare_s(self) -> float:
        return 0.0 if self.warm else self.pool.prepare_s

    def __repr__(self) -> str:
        return f"Coordinator({self.scene.name!r}, k={self.k}, mode={self.s.mode!r})"

    # -- seams: every call the coordinator makes (tests wrap them) ------------------------

    def _get(self, ref):
        return ray.get(ref)

    def _order(self, shard: int, passes: list[Pass], epoch: int) -> None:
        """Have `shard` generate these passes' camera rays, each with weight 1."""
        parcel = Parcel(epoch, {p.index: Fraction(1) for p in passes}, orders=tuple(passes))
        self.actors[shard].deliver.remote(parcel)

    def _poll(self, shard: int, epoch: int, collect: list[int] | None = None):
        return self.actors[shard].poll.remote(epoch, POLL_S, False, tuple(collect or ()))

    def _collect(self, shard: int, epoch: int, indices: list[int]):
        return self.actors[shard].collect.remote(epoch, indices)

    # -- the loop ----------------------------------------------------------------------

    def render_passes(self, passes: Iterator[Pass],
                      cancel: threading.Event | None = None
                      ) -> Iterator[tuple[Pass, np.ndarray, RenderStats]]:
        """Yield (pass, tile sums (n_pixels, 3) float64, stats) as passes finish, in any
        order. Stops admitting passes once `cancel` is set; closing the generator drops
        the passes still in flight."""
        t_start, c_start = time.perf_counter(), time.process_time()
        tiles = count_tiles(self.s)
        live: dict[int, _Live] = {}
        waiting: deque[Pass] = deque()  # admitted in order, once their tile is free
        attempts: dict[int, int] = {}
        exhausted = False
        epoch = self._begin()
        polls = {self._poll(s, epoch): s for s in range(self.k)}
        collects: dict = {}  # ref -> shard
        owed: list[list[int]] = [[] for _ in range(self.k)]  # finished passes' films, per shard
        watch = StallWatch(self.k)
        try:
            while True:
                stop = cancel is not None and cancel.is_set()
                if not stop:
                    exhausted = self._admit(passes, live, waiting, attempts, tiles, epoch,
                                            exhausted)
                if (stop or exhausted) and not live and not waiting:
                    self._last_poll(epoch)
                    return
                t0 = time.perf_counter()
                ready, _ = ray.wait([*polls, *collects], num_returns=1, timeout=POLL_S * 2)
                self.wait_s += time.perf_counter() - t0
                if not ready:
                    continue
                ref = ready[0]
                try:
                    if ref in polls:
                        shard = polls.pop(ref)
                        reply = self._get(ref)
                        self._on_poll(shard, reply, live, epoch)
                        watch.seen(reply)
                        pending = sum(not a.collecting for a in live.values())
                        if watch.stalled(pending > 0):
                            raise _Stalled(f"every shard idle for {STALL_S:.0f} s while "
                                           f"passes wait for weight")
                        done = [i for i, a in live.items()
                                if a.weight == 1 and not a.collecting]
                        for i in done:
                            live[i].collecting = True
                        for s in range(self.k):
                            owed[s] += done
                        if self.k < COLLECT_ON_POLL_FROM_K or pending - len(done) < self.k:
                            for s in range(self.k):  # at once: nothing waits for a poll
                                if owed[s]:
                                    collects[self._collect(s, epoch, owed[s])] = s
                                    owed[s] = []
                        polls[self._poll(shard, epoch, owed[shard])] = shard
                        owed[shard] = []
                        yield from self._on_collect(shard, (reply.incarnation,
                                                            reply.collected), live)
                    else:
                        shard = collects.pop(ref)
                        yield from self._on_collect(shard, self._get(ref), live)
                except (*SHARD_LOST, _Restarted, _Stalled) as e:
                    lost = sorted(live)
                    if isinstance(e, _Stalled):
                        log.warning("%s (lost); re-running %d passes in flight", e, len(lost))
                    else:
                        log.warning("shard %d lost (%s); re-running %d passes in flight",
                                    shard, type(e).__name__, len(lost))
                    for i in reversed(lost):  # oldest first again
                        self._requeue(live.pop(i).pass_, waiting, attempts)
                    self._end(epoch, unread=polls)
                    self._keep_totals()
                    self.reruns += 1
                    epoch = self._begin()
                    polls = {self._poll(s, epoch): s for s in range(self.k)}
                    collects = {}
                    owed = [[] for _ in range(self.k)]
                    watch = StallWatch(self.k)
        finally:
            self.wall_s += time.perf_counter() - t_start
            self.cpu_s += time.process_time() - c_start
            self._end(epoch, wait=False)

    def _last_poll(self, epoch: int) -> None:
        """The shards' final totals (and trace records). Every pass has its weight back, so
        no ray is left anywhere; a shard may still be accounting for its last step (its
        parcels leave first), so the poll settles that first."""
        for shard, ref in enumerate(self.actors[s].poll.remote(epoch, 0.0, True)
                                    for s in range(self.k)):
            try:
                reply = self._get(ref)
            except SHARD_LOST:  # the image is complete; only this shard's totals are lost
                log.warning("shard %d lost after the last pass; its totals are partial", shard)
                continue
            self.totals[shard] = reply
            if self.trace is not None:
                self.trace.add(reply.trace)

    def _admit(self, passes, live, waiting, attempts, tiles, epoch, exhausted) -> bool:
        """Admit passes up to the window, at most one live pass per tile, oldest first;
        order their camera rays from their shards. Returns whether `passes` ran out."""
        busy = {i % tiles for i in live}
        orders: dict[int, list[Pass]] = {}
        held: deque[Pass] = deque()
        while len(live) < self.window:
            if waiting:
                p = waiting.popleft()
            elif not exhausted and len(held) < self.window:
                p = next(passes, None)
                if p is None:
                    exhausted = True
                    continue
            else:
                break
            tile = p.index % tiles
            if tile in busy:  # an earlier sample chunk of this tile is still live
                held.append(p)
                continue
            busy.add(tile)
            attempts[p.index] = attempts.get(p.index, 0) + 1
            live[p.index] = _Live(p)
            if self.trace is not None:
                self.trace.on_admit(p.index)
            orders.setdefault(p.index % self.k, []).append(p)
        waiting.extendleft(reversed(held))
        for shard, ps in orders.items():
            self._order(shard, ps, epoch)
        return exhausted

    def _on_poll(self, shard: int, reply: PollReply, live: dict, epoch: int) -> None:
        self._check(shard, reply.incarnation)
        if reply.epoch != epoch:
            raise _Restarted(f"shard {shard} is not running this job (epoch {reply.epoch})")
        self.totals[shard] = reply
        if self.trace is not None:
            self.trace.add(reply.trace)
        for i, w in reply.returned:
            if i in live:
                live[i].weight += w
                if live[i].weight > 1:
                    raise RuntimeError(f"pass {i}: weight {live[i].weight} > 1 came back")

    def _on_collect(self, shard: int, reply: tuple, live: dict):
        incarnation, parts = reply
        self._check(shard, incarnation)
        for i, sums, stats in parts:
            a = live.get(i)
            if a is None:
                continue
            a.parts[shard] = (sums, stats)
            if len(a.parts) < self.k:
                continue
            del live[i]
            p = a.pass_
            total = FilmSums.zeros(p.n_pixels)
            st = RenderStats()
            for s in range(self.k):  # integers: the sum depends on neither order nor K
                part, pst = a.parts[s]
                if part is not None:
                    total += part
                    st.merge(RenderStats.from_dict(pst))
            yield p, total.to_float(), st

    def _check(self, shard: int, incarnation: str) -> None:
        if incarnation != self._incarnations[shard]:
            raise _Restarted(f"shard {shard} restarted (incarnation {incarnation[:8]})")

    def _requeue(self, p: Pass, waiting: deque, attempts: dict) -> None:
        if attempts.get(p.index, 0) >= MAX_PASS_ATTEMPTS:
            raise ShardsLost(f"pass {p.index} failed {MAX_PASS_ATTEMPTS} times; giving up")
        waiting.appendleft(p)

    def _begin(self) -> int:
        """A new epoch on every shard; waits until each answers (a dead one is restarted
        by Ray and comes back empty). Returns the epoch."""
        epoch = next(self._epochs)
        deadline = time.monotonic() + BEGIN_TIMEOUT_S
        while True:
            try:
                self.pool.resync()  # a restarted shard holds its start-up frame
                hold = (remote.HOLD_RAYS, remote.HOLD_S)
                send = (remote.SEND_RAYS, remote.SEND_S)
                refs = [a.begin.remote(epoch, self.s, self.actors, self.trace is not None, hold,
                                       send, remote.EMIT_RAYS, remote.CARRY_RAYS)
                        for a in self.actors]
                self._incarnations = ray.get(refs, timeout=BEGIN_TIMEOUT_S)
                self.totals = [None] * self.k
                return epoch
            except SHARD_LOST:
                if time.monotonic() > deadline:
                    break
                time.sleep(BEGIN_RETRY_S)
            except ray.exceptions.GetTimeoutError:
                break
        raise ShardsLost(f"shards did not come back within {BEGIN_TIMEOUT_S:g} s")

    def _end(self, epoch: int, wait: bool = True, unread: dict | None = None) -> None:
        """End run `epoch` on every shard; wait: take each live shard's final totals and
        the trace records no poll handed back (a run given up), before `_keep_totals`.
        unread: the run's polls not read yet (ref -> shard); ending the run wakes them, and
        the trace records they took are kept too (every step of the run is in the trace
        once, as in the totals)."""
        refs = [a.end.remote(epoch) for a in self.actors]
        if not wait:
            return
        deadline = time.monotonic() + BEGIN_TIMEOUT_S
        for ref in (unread or {}) if self.trace is not None else ():
            try:
                self.trace.add(ray.get(ref, timeout=max(0.0, deadline - time.monotonic())
                                       ).trace)
            except ray.exceptions.RayError:
                continue  # a dead shard's, or a failed wavefront's: nothing to keep
        for shard, ref in enumerate(refs):
            try:
                final = ray.get(ref, timeout=max(0.0, deadline - time.monotonic()))
            except (*SHARD_LOST, ray.exceptions.GetTimeoutError):
                continue  # a dead shard holds nothing; `_begin` waits for it to come back
            if final is None:
                continue  # not running this run: restarted, its totals gone with the process
            self.totals[shard] = final
            if self.trace is not None:
                self.trace.add(final.trace)

    def _keep_totals(self) -> None:
        """Add the shards' totals of a failed run to the job's (its CPU was spent)."""
        for s, t in enumerate(self.totals):
            if t is None:
                continue
            d = self._done_totals[s]
            for name in ("steps", "busy_s", "cpu_s", "wavefront_cpu_s", "bytes_in", "bytes_out",
                         "parcels_in", "parcels_out"):
                d[name] = d.get(name, 0) + getattr(t, name)
            for key in ("phase_s", "phase_cpu_s"):
                for name, v in getattr(t, key).items():
                    d.setdefault(key, {})[name] = d.get(key, {}).get(name, 0.0) + v
        self.totals = [None] * self.k

    def shard_totals(self) -> list[dict]:
        """Per shard, summed over this job's runs: steps, busy and CPU seconds (in total
        and per phase), bytes and parcels in and out."""
        out = []
        for s in range(self.k):
            d = {k: (dict(v) if isinstance(v, dict) else v)
                 for k, v in self._done_totals[s].items()}
            t = self.totals[s]
            if t is not None:
                for name in ("steps", "busy_s", "cpu_s", "wavefront_cpu_s", "bytes_in",
                             "bytes_out", "parcels_in", "parcels_out"):
                    d[name] = d.get(name, 0) + getattr(t, name)
                for key in ("phase_s", "phase_cpu_s"):
                    for name, v in getattr(t, key).items():
                        d.setdefault(key, {})[name] = d.get(key, {}).get(name, 0.0) + v
            out.append(d)
        return out

    def info(self) -> dict:
        wall = max(self.wall_s, 1e-9)
        shards = []
        for i, t in zip(self.shard_info, self.shard_totals(), strict=True):
            busy, cpu = float(t.get("busy_s", 0.0)), float(t.get("cpu_s", 0.0))
            named = sum(t.get("phase_cpu_s", {}).values())
            shards.append({
                "shard": i["shard"], "node": i.get("node"), "pid": i["pid"],
                "geometry_bytes": i["geometry_bytes"], "meshes": i.get("meshes"),
                "load_s": i.get("load_s"), "busy_s": round(busy, 4),
                "busy_fraction": round(busy / wall, 4), "cpu_s": round(cpu, 4),
                # The rest of cpu_s is Ray's threads: deliveries, polls, object transfers.
                "wavefront_cpu_s": round(float(t.get("wavefront_cpu_s", 0.0)), 4),
                "cpu_named_fraction": round(named / cpu, 4) if cpu and t.get("steps") else None,
                "phase_cpu_s": {k: round(v, 4) for k, v in
                                sorted(t.get("phase_cpu_s", {}).items())},
                "steps": int(t.get("steps", 0)), "calls": int(t.get("parcels_in", 0)),
                "parcels_out": int(t.get("parcels_out", 0)),
                "bytes_in": int(t.get("bytes_in", 0)), "bytes_out": int(t.get("bytes_out", 0))})
        return {
            "scene": self.scene.summary(),
            "renderer": "distributed",
            "mode": self.s.mode,
            "shards": self.k,
            "partition": self.partition.summary(),
            "shard_geometry_bytes": [i["geometry_bytes"] for i in self.shard_info],
            "max_shard_geometry_bytes": max(i["geometry_bytes"] for i in self.shard_info),
            "prepare_s": round(self.prepare_s, 4),
            "warm_pool": self.warm,
            "window": self.window,
            "coordinator_wait_s": round(self.wait_s, 4),
            "coordinator_cpu_s": round(self.cpu_s, 4),
            "cpu_s": round(self.cpu_s + sum(x["cpu_s"] for x in shards), 4),
            "reruns": self.reruns,
            "shard_stats": shards,
            "proxy_plan": None if self.plan is None else self.plan.to_dict(),
            "proxy_training": self.pool.training,
        }

    def close(self) -> None:
        """Hand the pool back (or close a private one); info() still answers after."""
        if self._closed:
            return
        self._closed = True
        if self._pools is not None:
            self._pools.release(self.pool)
        else:
            self.pool.close()
