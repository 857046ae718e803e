"""The Coordinator: drives one job's passes over a pool of K Shard actors, routing
ObjectRefs between shards and summing each finished pass's partial films. It reads only
manifests (ray counts per pass and target) and finished films: never a ray batch, which
moves shard to shard through the object store.

Pipelining (why a window of passes): a pass is a wavefront whose last bounces hold few
rays on few shards, so one pass at a time leaves shards idle. Up to `window` pass
attempts are in flight; the work waiting for a shard (camera rays of new passes, parcels
of any pass), oldest pass first and up to MAX_CALL_RAYS rays, goes out together in one
call as soon as the shard has fewer than MAX_QUEUED_CALLS calls queued, so a shard never
idles while work for it exists, calls stay few and large, and the oldest pass (the next
tile a user sees) is never starved by newer ones. Shard-to-shard sends were the
alternative; they would put pass accounting and retry in every shard, while here one loop
sees every pass end.

Failure: a shard that dies loses the partial films of every pass attempt it held, so
all live attempts are dropped and re-run under new tokens; a shard that restarted unseen
is caught when it hands back fewer calls for a token than were sent. A pass's film is
added only once all K parts of one attempt are back, so no sample is counted twice.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import ray
from ray.exceptions import ActorUnavailableError, RayActorError

from nprt.scene.meta import SceneMeta
from nprt.scene.model import Scene
from nprt.workers.passes import Pass
from nprt.workers.runtime.calltrace import TraceRecorder
from nprt.workers.runtime.pool import (  # noqa: F401 (ShardStartError re-exported)
    PoolRegistry,
    ShardPool,
    ShardsLost,
    ShardStartError,
)
from nprt.workers.runtime.protocol import Manifest, WorkItem
from nprt.workers.settings import RenderSettings
from nprt.workers.stats.counters import RenderStats

log = logging.getLogger(__name__)

MAX_PASS_ATTEMPTS = 4
MAX_QUEUED_CALLS = 2  # per shard: one running, one waiting, so it never idles
# Rays one call takes at most (camera rays count one per path): oldest passes go first, so
# the first tile shows early and a call's batches stay a few MB.
MAX_CALL_RAYS = 1 << 16
WINDOW_PER_SHARD = 3  # pass attempts in flight per shard
MIN_WINDOW = 4
CANCEL_POLL_S = 0.25
SHARD_LOST = (RayActorError, ActorUnavailableError)


class ShardStateLost(RuntimeError):
    """A shard restarted while it held part of a pass, so that part is gone."""


@dataclass
class _Attempt:
    """One try of one pass. pending: calls in flight plus parcels waiting, for this token."""

    pass_: Pass
    pending: int
    sent: np.ndarray  # (k,) int calls sent to each shard for this token
    collecting: bool = False
    parts: dict = field(default_factory=dict)  # shard -> (sums or None, stats dict, calls)


class Coordinator:
    """One job on a pool of shards: a warm one from `pools`, or else a private one that it
    closes with itself. scene: a stored scene's SceneMeta (nprt.scene.store.open_scene; the
    driver then holds no geometry) or an in-memory Scene. on_progress: per-mesh proxy
    training progress while a new pool starts (ShardPool)."""

    def __init__(self, scene: Scene | SceneMeta, settings: RenderSettings,
                 ray_address: str | None = None, proxy_dir=None,
                 shard_options: list[dict] | None = None, pools: PoolRegistry | None = None,
                 trace: bool = False, on_progress=None):
        self.scene, self.s, self.k = scene, settings, settings.shards
        self.trace = TraceRecorder(self.k) if trace else None  # every work call, for models
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
        self.window = max(MIN_WINDOW, WINDOW_PER_SHARD * self.k)
        self.fetched: list[type] = []  # what this coordinator read back, for the tests
        self.busy_s = np.zeros(self.k)
        self.bytes_in = np.zeros(self.k, np.int64)
        self.bytes_out = np.zeros(self.k, np.int64)
        self.calls = np.zeros(self.k, np.int64)
        self.wall_s = 0.0
        self.wait_s = 0.0
        self._tokens = itertools.count()
        self._lock = threading.Lock()

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

    def _get(self, ref):
        out = ray.get(ref)
        self.fetched.append(type(out))
        return out

    def _dispatch(self, shard: int, items: list[WorkItem], parcels: list):
        """Start one work call; returns (manifest ref, (k,) output refs)."""
        fn = self.actors[shard].work.options(num_returns=self.k + 1)
        refs = fn.remote(self._settings_ref, items, *parcels)
        return refs[0], refs[1:]

    def _collect(self, shard: int, tokens: list[int]):
        return self.actors[shard].collect.remote(tokens)

    def render_passes(self, passes: Iterator[Pass],
                      cancel: threading.Event | None = None
                      ) -> Iterator[tuple[Pass, np.ndarray, RenderStats]]:
        """Yield (pass, tile sums (n_pixels, 3) float64, stats) as passes finish, in any
        order. Stops admitting passes once `cancel` is set; closing the generator drops
        the passes still in flight."""
        k = self.k
        self._settings_ref = ray.put(self.s)
        live: dict[int, _Attempt] = {}
        retry: deque[Pass] = deque()
        attempts: dict[int, int] = {}
        # (token, rays, parcel ref or None = generate) waiting for each shard
        inbox: list[list] = [[] for _ in range(k)]
        queued = [0] * k  # calls in flight per shard
        waiting: dict = {}  # ref -> ("work", shard, tokens, outs) | ("collect", shard, tokens)
        exhausted = False
        t_start = time.perf_counter()
        try:
            while True:
                stop = cancel is not None and cancel.is_set()
                while not stop and len(live) < self.window:
                    p = retry.popleft() if retry else next(passes, None)
                    if p is None:
                        exhausted = True
                        break
                    attempts[p.index] = attempts.get(p.index, 0) + 1
                    token = next(self._tokens)
                    live[token] = _Attempt(p, pending=k, sent=np.zeros(k, np.int64))
                    for sid in range(k):
                        inbox[sid].append((token, p.n_paths, None))
                for sid in range(k):
                    if inbox[sid] and queued[sid] < MAX_QUEUED_CALLS:
                        inbox[sid] = self._send(sid, inbox[sid], live, waiting)
                        queued[sid] += 1
                if not waiting:
                    if stop or (exhausted and not live):
                        return
                    raise RuntimeError("coordinator stalled: passes live but nothing in flight")
                t0 = time.perf_counter()
                ready, _ = ray.wait(list(waiting), num_returns=1, timeout=CANCEL_POLL_S)
                self.wait_s += time.perf_counter() - t0
                if not ready:
                    continue
                what = waiting.pop(ready[0])
                try:
                    if what[0] == "work":
                        queued[what[1]] -= 1
                        self._on_work(ready[0], what, live, inbox)
                    else:
                        yield from self._on_collect(ready[0], what, live, retry, attempts)
                except SHARD_LOST as e:
                    if not any(t in live for t in what[2]):
                        continue  # a call of attempts already dropped for this loss
                    lost = list(live)
                    log.warning("shard %d lost (%s); re-running %d passes in flight",
                                what[1], type(e).__name__, len(lost))
                    for token in lost:
                        self._requeue(live.pop(token).pass_, retry, attempts)
                    inbox = [[] for _ in range(k)]
                    self._abort(lost)
                    self.pool.resync()  # a restarted shard holds its start-up frame
                for token in [t for t, a in live.items() if a.pending == 0 and not a.collecting]:
                    live[token].collecting = True
                    for sid in range(k):
                        waiting[self._collect(sid, [token])] = ("collect", sid, [token])
        finally:
            self.wall_s += time.perf_counter() - t_start
            self._settings_ref = None
            if live:  # canceled or failed: free what the shards hold for this job
                self._abort(list(live), wait=False)

    def _send(self, sid: int, entries: list, live: dict, waiting: dict) -> list:
        """One call to shard sid with its oldest waiting work, up to MAX_CALL_RAYS rays
        (at least one entry) and one pass per tile; returns the entries left over."""
        chosen, left, rays, tiles = [], [], 0, {}
        for entry in sorted(entries, key=lambda e: e[0]):  # tokens grow with pass age
            token, n, _ = entry
            p = live[token].pass_
            # A shard merges a call into one wavefront and finds a ray's pass by its
            # pixel, so a call holds one pass per tile.
            if tiles.setdefault((p.x0, p.y0), token) != token or \
                    (chosen and rays + n > MAX_CALL_RAYS):
                left.append(entry)
                continue
            chosen.append(entry)
            rays += n
        by_token: dict[int, list] = {}
        for token, _, ref in chosen:
            by_token.setdefault(token, []).append(ref)
        items, parcels = [], []
        for token, refs in by_token.items():
            att = live[token]
            att.pending += 1 - len(refs)  # the entries become one call
            att.sent[sid] += 1
            got = [r for r in refs if r is not None]
            items.append(WorkItem(token, att.pass_, None in refs, len(got)))
            parcels += got
        self.calls[sid] += 1
        m_ref, outs = self._dispatch(sid, items, parcels)
        if self.trace is not None:
            self.trace.on_dispatch(sid, by_token, m_ref, outs)
        waiting[m_ref] = ("work", sid, list(by_token), outs)
        return left

    def _on_work(self, ref, what, live: dict, inbox: list) -> None:
        _, sid, tokens, outs = what
        manifest: Manifest = self._get(ref)
        if self.trace is not None:
            self.trace.on_return(ref, manifest)
        self.busy_s[sid] += manifest.busy_s
        self.bytes_in[sid] += manifest.bytes_in
        self.bytes_out[sid] += manifest.bytes_out
        for token in tokens:
            att = live.get(token)
            if att is None:  # an attempt dropped after a loss; its rays go nowhere
                continue
            att.pending -= 1
            for target, count in enumerate(manifest.counts.get(token, ())):
                if count:
                    inbox[target].append((token, count, outs[target]))
                    att.pending += 1

    def _on_collect(self, ref, what, live: dict, retry: deque, attempts: dict):
        _, sid, tokens = what
        parts = self._get(ref)
        for token, sums, stats, calls in parts:
            att = live.get(token)
            if att is None:
                continue
            att.parts[sid] = (sums, stats, calls)
            if len(att.parts) < self.k:
                continue
            del live[token]
            short = [s for s, (_, _, c) in att.parts.items() if c != att.sent[s]]
            if short:
                log.warning("pass %d: shard %s ran fewer calls than sent (it restarted); "
                            "re-running it", att.pass_.index, short)
                self._requeue(att.pass_, retry, attempts)
                self.pool.resync()
                continue
            p = att.pass_
            sums_all = np.zeros((p.n_pixels, 3))
            st = RenderStats()
            for s in range(self.k):
                part, pst, _ = att.parts[s]
                if part is not None:
                    sums_all += part
                st.merge(RenderStats.from_dict(pst))
            yield p, sums_all, st

    def _requeue(self, p: Pass, retry: deque, attempts: dict) -> None:
        if attempts.get(p.index, 0) >= MAX_PASS_ATTEMPTS:
            raise ShardsLost(f"pass {p.index} failed {MAX_PASS_ATTEMPTS} times; giving up")
        retry.append(p)

    def _abort(self, tokens: list[int], wait: bool = True) -> None:
        """Drop these attempts on every shard; wait until every shard answers again (a dead
        one is restarted by Ray and comes back empty)."""
        for _ in range(MAX_PASS_ATTEMPTS * 20 if wait else 1):
            try:
                refs = [a.abort.remote(tokens) for a in self.actors]
                if wait:
                    ray.get(refs, timeout=30)
                return
            except SHARD_LOST:
                time.sleep(0.5)
            except ray.exceptions.GetTimeoutError:
                break
        raise ShardsLost(f"shards did not come back while dropping {len(tokens)} passes")

    def info(self) -> dict:
        wall = max(self.wall_s, 1e-9)
        shards = [{"shard": i["shard"], "node": i.get("node"), "pid": i["pid"],
                   "geometry_bytes": i["geometry_bytes"], "meshes": i.get("meshes"),
                   "load_s": i.get("load_s"),
                   "busy_s": round(float(self.busy_s[s]), 4),
                   "busy_fraction": round(float(self.busy_s[s]) / wall, 4),
                   "calls": int(self.calls[s]), "bytes_in": int(self.bytes_in[s]),
                   "bytes_out": int(self.bytes_out[s])}
                  for s, i in enumerate(self.shard_info)]
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
