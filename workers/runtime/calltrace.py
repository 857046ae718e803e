"""An optional record of a job's wavefront steps, for bench/network/netmodel.py, which replays
it with other node counts and link speeds: per step its shard, its wall-clock start and end
(time.time(), one clock on one host), CPU and busy seconds, the passes it ran and the
camera-ray orders it generated, the parcels it consumed (producer shard and step, rays,
bytes) and those it sent (target, rays, bytes); and the order in which passes were admitted.

Shards keep the records (a few list appends per step) and hand them back with their poll
replies; the coordinator only appends them here.
"""

from __future__ import annotations


class StepTrace:
    def __init__(self, k: int):
        self.k = k
        self.steps: list[dict] = []
        self.admitted: list[int] = []  # pass indices in admission order (re-runs again)

    def on_admit(self, index: int) -> None:
        self.admitted.append(index)

    def add(self, records: list[dict]) -> None:
        self.steps += records

    def to_dict(self) -> dict:
        steps = sorted(self.steps, key=lambda r: (r["shard"], r["step"]))
        return {"k": self.k, "steps": steps, "admitted": list(self.admitted)}
