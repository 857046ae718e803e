"""The Coordinator: starts K Shard actors, drives passes, routes ObjectRefs between
shards, and sums the partial framebuffers. It reads only manifests (ray counts per
target) and finished films: never a ray batch, which moves shard to shard through the
object store."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import ray
from ray.exceptions import GetTimeoutError, RayActorError
from ray.util.placement_group import placement_group, remove_placement_group
from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

from scene.model import Scene
from scene.partition import partition
from workers.passes import Pass
from workers.settings import RenderSettings
from workers.shard import Manifest, Shard, ShardConfig
from workers.stats import RenderStats
from workers.world import EVERYWHERE, ShardWorld

log = logging.getLogger(__name__)

MAX_PASS_ATTEMPTS = 4
# A shard killed mid-render restarts; one that keeps dying (in its constructor, say out of
# memory) must fail the job rather than restart for ever.
MAX_SHARD_RESTARTS = 3
READY_TIMEOUT_S = 300.0  # placement group and shard start-up, seconds


class ShardsLost(RuntimeError):
    """Shards did not come back after restarts: a node was lost. The job manager retries
    the render from its checkpoint on fresh shards."""


class ShardStartError(RuntimeError):
    """The shards could not be started; the message says which and why."""


class ShardStateLost(RuntimeError):
    """A shard restarted between two calls of a pass, so its partial film is gone."""


def make_plan(scene: Scene, part, settings: RenderSettings, proxy_dir=None, train=True):
    """Which meshes get a proxy, are replicated, or need nothing (proxies.policy)."""
    from proxies.cache import ProxyCache
    from proxies.config import DEFAULT_WIDTHS, ProxyConfig
    from proxies.policy import plan_proxies

    knobs = settings.proxy
    return plan_proxies(scene, part, target_accuracy=knobs.accuracy_target,
                        cache=ProxyCache(proxy_dir), train=train,
                        config=ProxyConfig(budget_s=knobs.budget_s),
                        widths=DEFAULT_WIDTHS if knobs.width is None else (knobs.width,))


_RAY_LOCK = threading.Lock()
_RAY_USERS = 0  # live coordinators on a Ray that this module started
_RAY_OWNED = False


def ensure_ray(address: str | None = None) -> bool:
    """Join `address`, or start a local Ray. Returns True when this call started it."""
    with _RAY_LOCK:
        if ray.is_initialized():
            return False
        ray.init(address=address, include_dashboard=False, logging_level=logging.WARNING,
                 log_to_driver=False)
        return True


def _acquire_ray(address: str | None) -> None:
    """Coordinators in several threads (the service runs jobs concurrently) share one
    Ray; the last one out shuts down a Ray that a coordinator started."""
    global _RAY_USERS, _RAY_OWNED
    with _RAY_LOCK:
        if not ray.is_initialized():
            ray.init(address=address, include_dashboard=False,
                     logging_level=logging.WARNING, log_to_driver=False)
            _RAY_OWNED = True
        _RAY_USERS += 1


def _release_ray() -> None:
    global _RAY_USERS, _RAY_OWNED
    with _RAY_LOCK:
        _RAY_USERS -= 1
        if _RAY_USERS == 0 and _RAY_OWNED:
            ray.shutdown()
            _RAY_OWNED = False


class Coordinator:
    def __init__(self, scene: Scene, settings: RenderSettings, ray_address: str | None = None,
                 proxy_dir=None, shard_options: list[dict] | None = None):
        self.scene, self.s, self.k = scene, settings, settings.shards
        t0 = time.perf_counter()
        self.partition = partition(scene, self.k)
        owner = np.asarray(self.partition.instance_shard, np.int32).copy()
        shard_meshes = [set(m) for m in self.partition.shard_meshes]
        self.plan, proxies = None, {}
        if settings.mode in ("proxy", "oracle"):
            # The oracle bounds the proxy mode, so it gets the same placement: meshes
            # lighter than their proxy are replicated (it trains nothing to learn that).
            self.plan = make_plan(scene, self.partition, settings, proxy_dir,
                                  train=settings.mode == "proxy")
            proxies = self.plan.proxies if settings.mode == "proxy" else {}
            for m in self.plan.replicated:  # cheaper to copy than to model
                owner[self.world_mesh_instances(scene, m)] = EVERYWHERE
                for held in shard_meshes:
                    held.add(m)
        self.world = ShardWorld.build(scene, owner)
        self.pg, self.actors, self._holds_ray = None, [], False
        try:
            self._start_shards(scene, settings, ray_address, proxies, shard_meshes,
                               shard_options)
        except BaseException:  # leave no placement group, actor or Ray reference behind
            self.close()
            raise
        self.prepare_s = time.perf_counter() - t0
        self.fetched: list[type] = []  # what this coordinator read back, for the tests
        log.info("started %d shards in %.2f s", self.k, self.prepare_s)

    def _start_shards(self, scene: Scene, settings: RenderSettings, ray_address, proxies,
                      shard_meshes, shard_options) -> None:
        """Put the world in the object store and start the K shards; close() undoes it."""
        _acquire_ray(ray_address)
        self._holds_ray = True
        world_ref = ray.put(self.world)
        all_ref = ray.put(dict(enumerate(scene.meshes))) if settings.mode == "oracle" else None
        cpus = ray.cluster_resources().get("CPU", 1.0)
        per_shard_cpu = min(1.0, cpus / self.k)
        # Gang-schedule the K shards: with several jobs at once, partial placements of
        # two jobs would otherwise wait on each other forever.
        if shard_options is None:
            self.pg = placement_group([{"CPU": per_shard_cpu}] * self.k, strategy="SPREAD")
            self._wait_ready(self.pg.ready(), f"a placement group of {self.k} x "
                             f"{per_shard_cpu:g} CPU ({cpus:g} CPUs in the cluster)")
        # A restarted actor re-reads its constructor arguments from the object store, so
        # they must outlive __init__ (ray-project/ray#53727).
        self._init_refs = [world_ref, all_ref]
        for sid in range(self.k):
            meshes_ref = ray.put({i: scene.meshes[i] for i in sorted(shard_meshes[sid])})
            # Only the proxies of meshes this shard does not hold.
            proxies_ref = ray.put({m: p for m, p in proxies.items() if m not in shard_meshes[sid]})
            opts = dict(max_restarts=MAX_SHARD_RESTARTS, max_task_retries=0,
                        num_cpus=per_shard_cpu)
            if self.pg is not None:
                opts["scheduling_strategy"] = PlacementGroupSchedulingStrategy(
                    self.pg, placement_group_bundle_index=sid)
            opts.update((shard_options or [{}] * self.k)[sid])
            actor = ray.remote(Shard).options(**opts).remote(
                ShardConfig(sid, self.k, settings), world_ref, meshes_ref, proxies_ref, all_ref)
            self.actors.append(actor)
            self._init_refs += [meshes_ref, proxies_ref]
        self.shard_info = [self._wait_ready(a.ready.remote(), f"shard {sid}")
                           for sid, a in enumerate(self.actors)]

    @staticmethod
    def _wait_ready(ref, what: str):
        """ray.get with a deadline: a shard that cannot start (dead node, out of memory in
        its constructor) fails the job with the reason instead of holding it forever."""
        try:
            return ray.get(ref, timeout=READY_TIMEOUT_S)
        except GetTimeoutError:
            raise ShardStartError(f"{what} was not ready within {READY_TIMEOUT_S:g} s"
                                  ) from None
        except RayActorError as e:
            raise ShardStartError(f"{what} did not start: {e}") from e

    @staticmethod
    def world_mesh_instances(scene: Scene, mesh: int) -> np.ndarray:
        return np.array([i for i, inst in enumerate(scene.instances) if inst.mesh == mesh], int)

    def __repr__(self) -> str:
        return f"Coordinator({self.scene.name!r}, k={self.k}, mode={self.s.mode!r})"

    def _get(self, refs):
        out = ray.get(refs)
        self.fetched.extend(type(x) for x in (out if isinstance(refs, list) else [out]))
        return out

    def run_pass(self, p: Pass) -> tuple[np.ndarray, RenderStats]:
        for attempt in range(1, MAX_PASS_ATTEMPTS + 1):
            try:
                return self._run_pass(p)
            except (RayActorError, ShardStateLost) as e:
                log.warning("pass %d attempt %d lost a shard (%s); re-running it",
                            p.index, attempt, type(e).__name__)
                self._abort(p)
        raise ShardsLost(f"pass {p.index} failed {MAX_PASS_ATTEMPTS} times; giving up")

    def _abort(self, p: Pass) -> None:
        """Drop the pass's partial films everywhere; restarted actors come back empty."""
        for _ in range(MAX_PASS_ATTEMPTS * 5):
            try:
                ray.get([a.abort_pass.remote(p.index) for a in self.actors])
                return
            except RayActorError:
                time.sleep(0.5)
        raise ShardsLost(f"shards did not come back while aborting pass {p.index}")

    def _call(self, shard: int, method: str, *args):
        """Start an actor call; returns (manifest ref, parcel refs (k,))."""
        fn = getattr(self.actors[shard], method).options(num_returns=self.k + 1)
        refs = fn.remote(*args)
        return refs[0], refs[1:]

    def _run_pass(self, p: Pass) -> tuple[np.ndarray, RenderStats]:
        wait_s = 0.0
        inflight: dict = {}
        busy = [False] * self.k
        calls = [0] * self.k  # calls sent per shard; an idle shard can die and restart unseen
        inbox: list[list] = [[] for _ in range(self.k)]
        for sid in range(self.k):  # each keeps the camera rays whose first box it owns
            m_ref, parcels = self._call(sid, "generate", p)
            inflight[m_ref] = (sid, parcels)
            busy[sid] = True
            calls[sid] += 1
        while inflight:
            t0 = time.perf_counter()
            ready, _ = ray.wait(list(inflight), num_returns=1)
            wait_s += time.perf_counter() - t0
            manifest: Manifest = self._get(ready[0])
            shard, parcels = inflight.pop(ready[0])
            busy[shard] = False
            for target, count in enumerate(manifest.counts):
                if count:
                    inbox[target].append(parcels[target])
            for sid in range(self.k):
                if inbox[sid] and not busy[sid]:
                    m_ref, out = self._call(sid, "process", p, *inbox[sid])
                    inflight[m_ref] = (sid, out)
                    inbox[sid], busy[sid] = [], True
                    calls[sid] += 1
        results = self._get([a.finish_pass.remote(p.index) for a in self.actors])
        sums = np.zeros((p.n_pixels, 3))
        stats = RenderStats()
        for sid, (part, st, ran) in enumerate(results):
            if ran != calls[sid]:
                raise ShardStateLost(f"shard {sid} ran {ran} of {calls[sid]} calls of pass "
                                     f"{p.index}: it restarted mid-pass")
            if part is not None:
                sums += part
            stats.merge(RenderStats.from_dict(st))
        stats.phase_s["coordinator_wait"] += wait_s
        return sums, stats

    def info(self) -> dict:
        return {
            "scene": self.scene.summary(),
            "renderer": "distributed",
            "mode": self.s.mode,
            "shards": self.k,
            "partition": self.partition.summary(),
            "shard_geometry_bytes": [i["geometry_bytes"] for i in self.shard_info],
            "max_shard_geometry_bytes": max(i["geometry_bytes"] for i in self.shard_info),
            "prepare_s": round(self.prepare_s, 4),
            "proxy_plan": None if self.plan is None else self.plan.to_dict(),
        }

    def close(self) -> None:
        if self.actors is None:
            return
        for a in self.actors:
            ray.kill(a, no_restart=True)
        self.actors = None
        if self.pg is not None:
            remove_placement_group(self.pg)
        if self._holds_ray:
            _release_ray()
