"""Shard pools: K Shard actors holding one scene's geometry placement, started once and
reused by every job on that scene (the service keeps them, least recently used first out,
within a memory bound). Starting a pool plans the placement from the scene's metadata
(training missing proxies as parallel Ray tasks), builds the world on a worker, and has each
shard load its own meshes from the scene store and warm every kernel, so a job on a warm
pool starts tracing at once. The driver holds no geometry of a stored scene
(`nprt.scene.store`), and imports none of the shard's libraries (`nprt.workers.runtime.remote`)."""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import OrderedDict

import numpy as np
import ray
from ray.util.placement_group import placement_group, remove_placement_group
from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

from nprt.scene.meta import SceneMeta
from nprt.scene.model import Scene
from nprt.scene.store import ObjectStoreSource
from nprt.workers.runtime.placement import make_plan, plan_placement  # noqa: F401 (make_plan re-exported)
from nprt.workers.runtime.protocol import MeshRequest, ShardConfig
from nprt.workers.runtime.raysession import acquire_ray, release_ray
from nprt.workers.runtime.remote import MAX_CONCURRENCY, ShardActor, build_world
from nprt.workers.settings import RenderSettings

log = logging.getLogger(__name__)

# A shard killed mid-render restarts; one that keeps dying (in its constructor, say out of
# memory) must fail the job rather than restart for ever.
MAX_SHARD_RESTARTS = 3
READY_TIMEOUT_S = 300.0  # placement group, and each shard's start-up and warm-up, seconds


class ShardsLost(RuntimeError):
    """Shards did not come back after restarts: a node was lost. The job manager retries
    the render from its checkpoint on fresh shards."""


class ShardStartError(RuntimeError):
    """The shards could not be started; the message says which and why."""


def _wait_ready(ref, what: str):
    """ray.get with a deadline: a shard that cannot start (dead node, out of memory in its
    constructor) fails the job with the reason instead of holding it forever."""
    try:
        return ray.get(ref, timeout=READY_TIMEOUT_S)
    except ray.exceptions.GetTimeoutError:
        raise ShardStartError(f"{what} was not ready within {READY_TIMEOUT_S:g} s") from None
    except ray.exceptions.RayActorError as e:
        raise ShardStartError(f"{what} did not start: {e}") from e


def pool_key(scene: Scene | SceneMeta, settings: RenderSettings) -> str:
    """Scene content plus the settings that decide what each shard holds."""
    h = hashlib.sha256()
    for m in scene.meshes:
        h.update(f"{m.content_hash}:{m.material}:{m.name}|".encode())
    h.update(np.ascontiguousarray(scene.instance_mesh, np.int64).tobytes())
    h.update(np.ascontiguousarray(scene.instance_transform, np.float64).tobytes())
    lights = (scene.quad_lights, scene.point_lights, scene.directional_lights,
              scene.environment, scene.camera)
    h.update(repr(lights).encode())
    for mat in scene.materials:
        h.update(repr((mat.name, mat.albedo, mat.emission)).encode())
        if mat.texture is not None:
            h.update(np.ascontiguousarray(mat.texture).tobytes())
    p = settings.proxy
    placement = (settings.shards, settings.mode, settings.byte_slack, p.accuracy_target,
                 p.width, p.steps)
    h.update(repr(placement).encode())
    return h.hexdigest()


def frame_key(scene: Scene | SceneMeta) -> str:
    """What changes between frames: instance transforms and lights."""
    h = hashlib.sha256(np.ascontiguousarray(scene.instance_transform, np.float64).tobytes())
    h.update(repr((scene.quad_lights, scene.point_lights, scene.directional_lights)).encode())
    return h.hexdigest()


def first_cold_per_node(shard_info: list[dict]) -> list[int]:
    """The lowest shard id on each node whose shards found numba's cache cold (`ready()`'s
    "cold_kernels"), in id order: they warm first, alone on their node."""
    first: dict = {}
    for sid, info in enumerate(shard_info):
        if info.get("cold_kernels"):
            first.setdefault(info.get("node"), sid)
    return sorted(first.values())


class ShardPool:
    """K started, warmed Shard actors for one scene and placement.

    scene: a SceneMeta with a mesh source (a stored scene: each shard loads its own
    meshes, the driver none), or an in-memory Scene (its meshes are put in Ray's object
    store once, and each shard gets only its own). shard_options: per-shard extra actor
    options (tests pin shards to nodes with them); without them the K shards are
    gang-scheduled in a SPREAD placement group. on_progress: sees per-mesh proxy
    training progress (a list of dicts) while the pool starts."""

    def __init__(self, scene: Scene | SceneMeta, settings: RenderSettings,
                 ray_address: str | None = None, proxy_dir=None,
                 shard_options: list[dict] | None = None, on_progress=None):
        t0 = time.perf_counter()
        meta = SceneMeta.of(scene)
        self.key = pool_key(meta, settings)
        self.jobs = 0  # coordinators that ran on it
        self.registered = False  # kept by a PoolRegistry
        self.scene_name, self.k, self.mode = meta.name, settings.shards, settings.mode
        self.pg, self.actors, self.warm_s, self._init_refs = None, [], [0.0], []
        self.training: list[dict] = []  # per-mesh proxy training, when any ran
        self.shown, self._world_ref = frame_key(meta), None  # None: the start-up world
        acquire_ray(ray_address)
        try:
            # Meshes of a stored scene stay where they are; an in-memory one's go to
            # the object store once (each shard then fetches only its own).
            if meta.source is None and isinstance(scene, SceneMeta):
                raise ValueError(f"scene {meta.name!r}: metadata without a mesh source; "
                                 f"pass the Scene, or metadata from nprt.scene.store.open_scene")
            self.source = meta.source or ObjectStoreSource.put(scene.meshes)
            trainer = None
            if settings.mode == "proxy":
                from nprt.proxies.tasks import RayTrainer

                trainer = RayTrainer(self.source, proxy_dir, on_progress,
                                     names={i: m.name for i, m in enumerate(meta.meshes)})
            placed = plan_placement(meta, settings, proxy_dir, trainer)
            self.training = trainer.progress if trainer is not None else []
            self.partition, self.plan, self.owner = placed.partition, placed.plan, placed.owner
            self.instance_mesh = np.array(meta.instance_mesh, np.int32)
            self.shard_meshes = placed.shard_meshes
            self._start(meta, settings, placed.shard_meshes, placed.proxies, shard_options)
        except BaseException:
            self.close()
            raise
        self.prepare_s = time.perf_counter() - t0
        self.last_used = time.monotonic()
        log.info("pool %s: %d shards of %r ready in %.2f s (warm-up %.2f s)", self.key[:12],
                 self.k, meta.name, self.prepare_s, max(self.warm_s))

    def _start(self, meta, settings, shard_meshes, proxies, shard_options) -> None:
        # The instance table (with its BVH) is built on a worker; the driver holds only
        # the reference.
        world_ref = build_world.remote(meta, self.owner)
        every = MeshRequest(self.source, tuple(range(len(meta.meshes))))
        all_req = every if settings.mode == "oracle" else None
        cpus = ray.cluster_resources().get("CPU", 1.0)
        per_shard_cpu = min(1.0, cpus / self.k)
        # Gang-schedule the K shards: with several jobs at once, partial placements of
        # two jobs would otherwise wait on each other forever.
        if shard_options is None:
            self.pg = placement_group([{"CPU": per_shard_cpu}] * self.k, strategy="SPREAD")
            _wait_ready(self.pg.ready(), f"a placement group of {self.k} x "
                        f"{per_shard_cpu:g} CPU ({cpus:g} CPUs in the cluster)")
        # The meshes, world and proxies reach each actor as arguments of `load`, not of its
        # constructor: a restarted actor (Ray re-runs only the constructor) is loaded again
        # by `resync`, and no constructor argument lives in the object store (Ray prints an
        # error line for those on the console; an in-memory scene's meshes are there).
        self._init_refs = []  # `ShardActor.load`'s arguments per shard, kept for restarts
        for sid in range(self.k):
            held = set(shard_meshes[sid])
            # Only the proxies of meshes this shard does not hold.
            proxies_ref = ray.put({m: p for m, p in proxies.items() if m not in held})
            # No task events: Ray would record every call (a parcel is one) and ship the
            # records to the GCS for its dashboard and state API, which nprt does not read
            # (raysession's docstring has the measurement).
            opts = dict(max_restarts=MAX_SHARD_RESTARTS, max_task_retries=0,
                        num_cpus=per_shard_cpu, max_concurrency=MAX_CONCURRENCY,
                        enable_task_events=False)
            if self.pg is not None:
                opts["scheduling_strategy"] = PlacementGroupSchedulingStrategy(
                    self.pg, placement_group_bundle_index=sid)
            opts.update((shard_options or [{}] * self.k)[sid])
            actor = ray.remote(ShardActor).options(**opts).remote(
                ShardConfig(sid, self.k, settings))
            self.actors.append(actor)
            self._init_refs.append((world_ref, proxies_ref,
                                    MeshRequest(self.source, tuple(shard_meshes[sid])), all_req))
        # Every shard loads (then warms) at once: submitted together, waited for in turn.
        loads = [a.load.remote(*self._init_refs[sid]) for sid, a in enumerate(self.actors)]
        self.shard_info = [_wait_ready(ref, f"shard {sid}") for sid, ref in enumerate(loads)]
        # On a cold numba cache (a fresh install) one shard a node compiles the kernels into
        # that node's cache first and the others then load them: warmed all at once, each
        # would compile them all, K times the CPU on cores they share.
        first = first_cold_per_node(self.shard_info)
        self.warm_s = [0.0] * self.k
        for wave in (first, [sid for sid in range(self.k) if sid not in first]):
            warms = [(sid, self.actors[sid].warm.remote()) for sid in wave]
            for sid, ref in warms:
                self.warm_s[sid] = _wait_ready(ref, f"shard {sid} (warming its kernels)")

    def show(self, scene: Scene | SceneMeta) -> None:
        """Make every shard render `scene`: a frame of the pool's scene (its meshes and
        instance meshes), with its own instance transforms and lights. Only the instance
        table and lights travel, built from metadata (per-mesh bounds; no mesh is loaded
        here); each instance keeps its owner, so no geometry moves and no proxy changes.
        A no-op when the shards show it already."""
        key = frame_key(scene)
        if key == self.shown:
            return
        if not np.array_equal(scene.instance_mesh, self.instance_mesh):
            raise ValueError(f"{self!r} cannot show scene {scene.name!r}: it is not a frame "
                             f"of the pool's scene (its instances place other meshes)")
        self._world_ref = build_world.remote(SceneMeta.of(scene), self.owner)
        self.resync()
        self.shown = key

    def resync(self) -> None:
        """Load a restarted shard again (a no-op for the others) and send every shard the
        shown world (a restarted one comes back with the start-up world)."""
        ray.get([a.load.remote(*refs) for a, refs in zip(self.actors, self._init_refs,
                                                          strict=True)])
        if self._world_ref is not None:
            ray.get([a.set_world.remote(self._world_ref) for a in self.actors])

    def __repr__(self) -> str:
        return f"ShardPool({self.scene_name!r}, k={self.k}, mode={self.mode!r})"

    @property
    def nbytes(self) -> int:
        """Geometry bytes held by all its shards (what the service's memory bound counts)."""
        return int(sum(i["geometry_bytes"] for i in self.shard_info))

    def alive(self, timeout_s: float = 10.0) -> bool:
        try:
            ray.get([a.ready.remote() for a in self.actors], timeout=timeout_s)
            return True
        except Exception:  # dead for good, or not answering: not worth reusing
            return False

    def close(self) -> None:
        if self.actors is None:
            return
        for a in self.actors:
            ray.kill(a, no_restart=True)
        # Drop every handle and reference before Ray may shut down: one released after
        # that makes the core worker wait for a GCS that is gone, then exit the process.
        self.actors, self._init_refs, self.source = None, [], None
        if self.pg is not None:
            remove_placement_group(self.pg)
            self.pg = None
        release_ray()


class PoolRegistry:
    """Warm pools by key; idle ones are evicted least recently used first when the held
    geometry would exceed max_bytes, when there are more than max_pools, or when a new pool
    needs the CPUs they reserve."""

    def __init__(self, max_bytes: int = 8 << 30, max_pools: int = 4):
        self.max_bytes, self.max_pools = max_bytes, max_pools
        self._pools: OrderedDict[str, ShardPool] = OrderedDict()
        self._busy: set[str] = set()
        self._lock = threading.Lock()
        self.started = 0  # pools created, for tests and statistics

    def acquire(self, scene: Scene, settings: RenderSettings, **pool_kwargs) -> ShardPool:
        """A warm pool for (scene, placement), exclusive until `release`: the registered
        one if it is idle and alive, else a new one (registered unless the key is busy)."""
        key = pool_key(scene, settings)
        with self._lock:
            pool = self._pools.get(key)
            reuse = pool is not None and key not in self._busy
            if reuse:
                self._busy.add(key)
                self._pools.move_to_end(key)
        if reuse and not pool.alive():
            log.warning("%r lost its shards; starting a new one", pool)
            self._drop(key)
            reuse = False
        if reuse:
            return pool
        self._make_room(settings)
        pool = ShardPool(scene, settings, **pool_kwargs)
        self.started += 1
        with self._lock:
            pool.registered = key not in self._pools  # else a private pool for this job
            if pool.registered:
                self._pools[key] = pool
                self._busy.add(key)
        return pool

    def release(self, pool: ShardPool) -> None:
        pool.last_used = time.monotonic()
        if not pool.registered:
            pool.close()
            return
        with self._lock:
            self._busy.discard(pool.key)
        self._evict(keep_bytes=self.max_bytes, keep_pools=self.max_pools)

    def _make_room(self, settings: RenderSettings) -> None:
        """Evict idle pools until the new one fits the bounds and the free CPUs."""
        self._evict(keep_bytes=self.max_bytes, keep_pools=self.max_pools - 1)
        if not ray.is_initialized():
            return
        want = min(1.0, ray.cluster_resources().get("CPU", 1.0) / max(settings.shards, 1))
        while ray.available_resources().get("CPU", 0.0) < want * settings.shards:
            if not self._evict_one():
                return

    def _evict(self, keep_bytes: int, keep_pools: int) -> None:
        while True:
            with self._lock:
                held = sum(p.nbytes for p in self._pools.values())
                over = held > keep_bytes or len(self._pools) > keep_pools
            if not over or not self._evict_one():
                return

    def _evict_one(self) -> bool:
        with self._lock:
            idle = [k for k in self._pools if k not in self._busy]
            if not idle:
                return False
            pool = self._pools.pop(idle[0])
        log.info("evicting %r (least recently used)", pool)
        pool.close()
        return True

    def _drop(self, key: str) -> None:
        with self._lock:
            pool = self._pools.pop(key, None)
            self._busy.discard(key)
        if pool is not None:
            pool.close()

    def close(self) -> None:
        with self._lock:
            pools, self._pools = list(self._pools.values()), OrderedDict()
            self._busy.clear()
        for p in pools:
            p.close()
