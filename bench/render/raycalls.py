"""Ray's own CPU per parcel: two actors on this host, one sending parcels of n rays to the
other (`deliver`, as the shards do), process CPU on each side per call. A straight-line
fit over the sizes gives a fixed cost per call and a cost per byte, per side; the
dedicated-core model of bench_visits adds them to each in-process step."""

from __future__ import annotations

import time

import numpy as np
import ray

from nprt.workers.runtime.protocol import Parcel
from nprt.workers.runtime.raysession import acquire_ray, release_ray
from nprt.workers.wavefront.batch import RayBatch


# As the shards run (workers/runtime/pool.py, remote.py): no task events, and `deliver`
# returns no object ref.
@ray.remote(num_cpus=0, max_concurrency=8, enable_task_events=False)
class _Sink:
    def __init__(self):
        self.n = 0

    @ray.method(num_returns=0)
    def deliver(self, parcel) -> None:
        self.n += 1

    def cpu(self) -> tuple[float, int]:
        return time.process_time(), self.n

    def send_to(self, peer, parcel, n: int) -> float:
        c0 = time.process_time()
        for _ in range(n):
            peer.deliver.remote(parcel)
        return time.process_time() - c0


def _batch(rows: int) -> RayBatch:
    return RayBatch(**{name: np.zeros((rows,) if w is None else (rows, w), dt)
                       for name, (w, dt) in RayBatch._SPEC.items()})


def parcel_cost(sizes=(100, 1000, 5000), calls: int = 300, repeats: int = 3) -> dict:
    """{"send_s", "receive_s": fixed seconds per call; "send_s_per_byte",
    "receive_s_per_byte"; "points": [(rows, bytes, send s, receive s)] (medians)}."""
    acquire_ray(None)
    try:
        a, b = _Sink.remote(), _Sink.remote()
        ray.get([a.cpu.remote(), b.cpu.remote()])
        points = []
        for rows in sizes:
            parcel = Parcel(0, {0: 1}, _batch(rows))
            runs = []
            for _ in range(repeats):
                c0, n0 = ray.get(b.cpu.remote())
                send = ray.get(a.send_to.remote(b, parcel, calls))
                while ray.get(b.cpu.remote())[1] < n0 + calls:
                    time.sleep(0.02)
                c1, _ = ray.get(b.cpu.remote())
                runs.append((send / calls, (c1 - c0) / calls))
            s, r = np.median(np.array(runs), axis=0)
            points.append((rows, parcel.nbytes, float(s), float(r)))
        for actor in (a, b):
            ray.kill(actor)
    finally:
        release_ray()
    nbytes = np.array([p[1] for p in points], float)
    fit = {side: np.polyfit(nbytes, [p[i] for p in points], 1)
           for side, i in (("send", 2), ("receive", 3))}
    return {"send_s": max(0.0, float(fit["send"][1])),
            "send_s_per_byte": max(0.0, float(fit["send"][0])),
            "receive_s": max(0.0, float(fit["receive"][1])),
            "receive_s_per_byte": max(0.0, float(fit["receive"][0])), "points": points}


def with_ray_cost(trace: dict, cost: dict) -> np.ndarray:
    """(n_steps,) seconds per step on a dedicated core: its in-process CPU plus Ray's cost
    for each parcel it sent and received."""
    out = []
    for st in trace["steps"]:
        send = sum(cost["send_s"] + cost["send_s_per_byte"] * out[2] for out in st["outputs"])
        recv = sum(cost["receive_s"] + cost["receive_s_per_byte"] * inp[3]
                   for inp in st["inputs"])
        out.append(st["cpu_s"] + send + recv)
    return np.array(out)
