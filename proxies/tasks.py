"""Proxy training across the cluster: one Ray task per mesh that needs a proxy, all in
flight at once. Each task loads its mesh from the scene store itself (the driver never
holds it), trains the narrowest width meeting the target (as `narrowest_proxy` does in
process) and writes the proxies to the proxy cache by content hash; the planner then reads
them from there. The cache directory must be one every node can write and the driver can
read (a shared filesystem on a real cluster), and the nodes need the `train` extra.

Progress per mesh (queued, training, done or failed, with seconds and accuracy) goes to
`on_progress` as a list of dicts each time a task ends; a task that fails (an exception,
a lost node) leaves its mesh traced exactly, with the reason in the plan.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

TRAIN_CPUS = 1  # per task; torch in the task uses nprt.proxies.train.TRAIN_THREADS threads


def train_mesh(source, mesh: int, config, widths, target: float, cache_dir) -> dict:
    """The body of one task: load mesh `mesh` from `source`, fill the cache with its
    narrowest proxy meeting `target`. Returns {"tried": {width: accuracy}, "why": reason
    no proxy could be had or None, "load_s", "train_s"}."""
    from nprt.proxies.cache import ProxyCache
    from nprt.proxies.policy import narrowest_proxy

    t0 = time.perf_counter()
    m = source.load_meshes([mesh])[mesh]
    t1 = time.perf_counter()
    # An error inside narrowest_proxy is returned as `why`; let it fail the task instead,
    # so the driver sees one failure path.
    proxy, tried, why = narrowest_proxy(m, config, widths, target, ProxyCache(cache_dir),
                                        train=True, progress=False)
    if proxy is None:
        raise RuntimeError(why or f"no proxy for mesh {mesh}")
    return {"tried": tried, "load_s": t1 - t0, "train_s": time.perf_counter() - t1}


class RayTrainer:
    """Trains proxies as parallel Ray tasks (plan_proxies' `trainer`). source: the
    scene's MeshSource; cache_dir: the proxy cache (None: the default one);
    task_options: extra `.options()` of every task; parallel=False runs the tasks one
    after another (the benchmark's baseline); names: mesh index -> name, for progress."""

    def __init__(self, source, cache_dir=None, on_progress: Callable[[list], None] | None = None,
                 task_options: dict | None = None, parallel: bool = True,
                 names: dict[int, str] | None = None):
        self.source, self.cache_dir, self.names = source, cache_dir, names or {}
        self.on_progress, self.parallel = on_progress, parallel
        self.task_options = task_options or {}
        self.progress: list[dict] = []  # per mesh, in the order asked
        self.wall_s = 0.0

    def __call__(self, meshes: list[int], config, widths, target: float) -> dict[int, str]:
        import ray

        remote = ray.remote(train_mesh).options(num_cpus=TRAIN_CPUS, max_retries=0,
                                                **self.task_options)
        self.progress = [{"mesh": i, "name": self.names.get(i), "state": "queued", "seconds": None}
                         for i in meshes]
        row = {p["mesh"]: p for p in self.progress}
        t0 = time.perf_counter()
        failed: dict[int, str] = {}
        todo = list(meshes)
        running: dict = {}
        while todo or running:
            while todo and (self.parallel or not running):
                i = todo.pop(0)
                ref = remote.remote(self.source, i, config, tuple(widths), target, self.cache_dir)
                running[ref] = (i, time.perf_counter())
                row[i]["state"] = "training"
            self._report()
            (ref,), _ = ray.wait(list(running), num_returns=1)
            i, started = running.pop(ref)
            r = row[i]
            r["seconds"] = round(time.perf_counter() - started, 3)
            try:
                out = ray.get(ref)
                r["state"] = "done"
                r["accuracy"] = max(out["tried"].values()) if out["tried"] else None
                r["widths"] = sorted(out["tried"])
            except Exception as e:  # a failed task: this mesh is traced exactly
                cause = getattr(e, "cause", None) or e
                why = f"training task failed: {type(cause).__name__}: {cause}"
                log.warning("proxy training for mesh %d failed: %s", i, why)
                r["state"], r["error"] = "failed", why[:500]
                failed[i] = why
        self.wall_s = time.perf_counter() - t0
        self._report()
        return failed

    def _report(self) -> None:
        if self.on_progress is not None:
            try:
                self.on_progress([dict(p) for p in self.progress])
            except Exception:  # a progress sink must not fail the training
                log.exception("proxy training progress callback failed")
