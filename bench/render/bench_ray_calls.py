"""What Ray itself costs per parcel, whole processes counted: two threaded actors (as the
shards are: `max_concurrency`), one sending parcels of n rays (nprt's `Parcel` of a
`RayBatch`, packed as the shards pack it) to the other's `deliver`, under several Ray
settings. Each variant runs in a fresh local Ray of its own (a system config is fixed when
Ray starts), in a subprocess.

Per call, in microseconds of CPU, from /proc/<pid>/stat (every thread of the process, Ray's
included; `time.process_time` inside an actor would miss none of them either, but the
raylet and GCS are separate processes):
- `send_thread`: the calling thread's (serialising the parcel, submitting the call: in a
  shard this is the wavefront thread's `send` phase);
- `send_ray`: the rest of the sending process (Ray's threads: the reply, task events,
  reference counting, plasma);
- `receive`: the whole receiving process (the call's arguments, the executor thread, the
  reply);
- `raylet`, `gcs`: the node's raylet and the GCS.
Idle CPU of each actor over `--idle` seconds is subtracted from every window and reported
per second (`idle_*_pct`: percent of a core).

    .venv/bin/python -m bench.render.bench_ray_calls [--variants default no_task_events ...]
        [--sizes 100 5000] [--calls 2000] [--rounds 3] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import ray

from bench.common import proc_cpu
from nprt.workers.runtime.raysession import RAY_SYSTEM_CONFIG

# name -> (ray.init _system_config, actor options, deliver's num_returns): the candidates
# of issue 20's s8 brief.
_INLINE = {"max_direct_call_object_size": 1 << 20}
VARIANTS = {
    "default": ({}, {}, 1),
    "no_task_events": ({}, {"enable_task_events": False}, 1),
    "no_metrics": ({"enable_metrics_collection": False}, {}, 1),
    "no_task_events_no_metrics": ({"enable_metrics_collection": False},
                                  {"enable_task_events": False}, 1),
    "no_returns": ({}, {}, 0),
    "no_returns_no_task_events": ({}, {"enable_task_events": False}, 0),
    "inline_1mb": (_INLINE, {}, 1),
    "inline_1mb_no_task_events": (_INLINE, {"enable_task_events": False}, 1),
    "inline_1mb_no_returns_no_task_events": (_INLINE, {"enable_task_events": False}, 0),
    "inline_4mb_no_returns_no_task_events": ({"max_direct_call_object_size": 4 << 20},
                                             {"enable_task_events": False}, 0),
    # what the shards run with: RAY_SYSTEM_CONFIG, pool.py's options, remote.py's deliver
    "nprt": (RAY_SYSTEM_CONFIG, {"enable_task_events": False}, 0),
    # and deliveries run by one thread of their own (a concurrency group), not by any of
    # the actor's 8, which then take turns at the GIL
    "nprt_one_delivery_thread": (RAY_SYSTEM_CONFIG, {"enable_task_events": False,
                                                     "concurrency_groups": {"deliver": 1}}, 0),
}


def _batch(rows: int):
    from nprt.workers.wavefront.batch import RayBatch

    rng = np.random.default_rng(rows)
    return RayBatch(**{name: rng.random((rows,) if w is None else (rows, w)).astype(dt)
                       for name, (w, dt) in RayBatch._SPEC.items()})


class _Peer:
    """A threaded actor that counts deliveries (a shard's `deliver` only appends too)."""

    def __init__(self):
        self.n = 0
        self.cv = threading.Condition()

    def pid(self) -> int:
        return os.getpid()

    def deliver(self, parcel) -> None:
        with self.cv:
            self.n += 1
            self.cv.notify_all()

    @ray.method(num_returns=0)
    def deliver0(self, parcel) -> None:
        self.deliver(parcel)

    def wait_for(self, n: int) -> int:
        with self.cv:
            self.cv.wait_for(lambda: self.n >= n, timeout=120)
            return self.n

    def send(self, peer, rows: int, calls: int, num_returns: int = 1,
             group: str | None = None) -> float:
        """Sends `calls` parcels of `rows` rays to peer (`deliver`, or `deliver0` that
        returns no object ref; in concurrency group `group`); the calling thread's CPU
        seconds."""
        from nprt.workers.runtime.protocol import Parcel

        batch = _batch(rows)
        deliver = peer.deliver0 if num_returns == 0 else peer.deliver
        if group:
            deliver = deliver.options(concurrency_group=group)
        c0 = time.thread_time()
        for i in range(calls):
            deliver.remote(Parcel(0, {i: 1}, batch))
        return time.thread_time() - c0


def measure(actor_options: dict, num_returns: int, sizes, calls: int, rounds: int,
            idle_s: float) -> dict:
    """In a running Ray: per-call CPU (us) by side for each size, and idle CPU."""
    node = ray._private.worker._global_node
    system = {name: node.all_processes[key][0].process.pid
              for name, key in (("raylet", "raylet"), ("gcs", "gcs_server"))
              if node is not None and node.all_processes.get(key)}
    options = dict(actor_options)
    groups = options.pop("concurrency_groups", None)  # only ray.remote takes these
    cls = ray.remote(_Peer) if groups is None else ray.remote(concurrency_groups=groups)(_Peer)
    cls = cls.options(num_cpus=0, max_concurrency=8, **options)
    group = next(iter(groups or {}), None)
    a, b = cls.remote(), cls.remote()
    pids = {"send": ray.get(a.pid.remote()), "receive": ray.get(b.pid.remote()), **system}
    ray.get(a.send.remote(b, 10, 50, num_returns, group))  # warm both sides (imports, first calls)
    ray.get(b.wait_for.remote(50))
    time.sleep(1.0)
    c0, t0 = {k: proc_cpu(p) for k, p in pids.items()}, time.perf_counter()
    time.sleep(idle_s)
    idle = {k: (proc_cpu(p) - c0[k]) / (time.perf_counter() - t0) for k, p in pids.items()}
    out = {"idle_pct": {k: round(100 * v, 2) for k, v in idle.items()}, "sizes": {}}
    done = 50
    for rows in sizes:
        runs = []
        for _ in range(rounds):
            c0, t0 = {k: proc_cpu(p) for k, p in pids.items()}, time.perf_counter()
            thread_s = ray.get(a.send.remote(b, rows, calls, num_returns, group))
            done = ray.get(b.wait_for.remote(done + calls))
            time.sleep(1.1)  # Ray's deferred work: task events go out every second
            dt = time.perf_counter() - t0
            cpu = {k: proc_cpu(p) - c0[k] - idle[k] * dt for k, p in pids.items()}
            runs.append({"send_thread": thread_s, "send_ray": cpu["send"] - thread_s,
                         "receive": cpu["receive"],
                         **{k: cpu[k] for k in system}})
        med = {k: round(1e6 * float(np.median([r[k] for r in runs])) / calls, 1)
               for k in runs[0]}
        from nprt.workers.runtime.protocol import Parcel

        med["bytes"] = Parcel(0, {0: 1}, _batch(rows)).nbytes
        out["sizes"][rows] = med
    for actor in (a, b):
        ray.kill(actor)
    return out


def _one(variant: str, sizes, calls: int, rounds: int, idle_s: float) -> dict:
    """One variant in a fresh local Ray (this process is its driver)."""
    import logging

    system_config, actor_options, num_returns = VARIANTS[variant]
    config = dict(system_config) if system_config else None  # ray.init adds to it
    ray.init(address="local", num_cpus=4, include_dashboard=False, log_to_driver=False,
             logging_level=logging.ERROR, _system_config=config)
    try:
        return measure(actor_options, num_returns, sizes, calls, rounds, idle_s)
    finally:
        ray.shutdown()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--sizes", nargs="+", type=int, default=[100, 5000])
    ap.add_argument("--calls", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--idle", type=float, default=5.0, help="seconds of idle measurement")
    ap.add_argument("--repeat", type=int, default=1, help="passes over the variants")
    ap.add_argument("--out", help="JSON file for the results")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--smoke", action="store_true", help="one variant, a few calls")
    args = ap.parse_args(argv)
    if args.smoke:
        args.variants, args.sizes, args.calls, args.rounds, args.idle = \
            ["nprt"], [100], 20, 1, 0.2
    if args.one:
        print(json.dumps(_one(args.variants[0], args.sizes, args.calls, args.rounds,
                              args.idle)))
        return
    env = {**os.environ, "RAY_ADDRESS": "local"}  # a Ray of its own, whatever is running
    results = []
    for rep in range(args.repeat):
        for v in args.variants:
            cmd = [sys.executable, "-m", "bench.render.bench_ray_calls", "--one",
                   "--variants", v, "--sizes", *map(str, args.sizes), "--calls",
                   str(args.calls), "--rounds", str(args.rounds), "--idle", str(args.idle)]
            res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
            if res.returncode != 0:
                raise SystemExit(f"variant {v} failed:\n{res.stderr[-3000:]}")
            r = {"variant": v, "repeat": rep, **json.loads(res.stdout.strip().splitlines()[-1])}
            results.append(r)
            idle = " ".join(f"{k} {x:.2f}%" for k, x in r["idle_pct"].items())
            print(f"{v:28s} idle: {idle}")
            for rows, m in r["sizes"].items():
                total = sum(x for k, x in m.items() if k != "bytes")
                print(f"  {rows:>5} rays {m['bytes']:>7} B  us/call: " + " ".join(
                    f"{k} {x:.0f}" for k, x in m.items() if k != "bytes") + f"  total {total:.0f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"load_average": os.getloadavg(), "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
