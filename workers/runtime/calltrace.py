"""An optional record of a job's wavefront steps, for bench/network/netmodel.py, which replays
it with other node counts and link speeds: per step its shard, its wall-clock start and end
(time.time(), one clock on one host), CPU and busy seconds, the passes it ran and the
camera-ray orders it generated, the parcels it consumed (producer shard and step, rays,
bytes) and those it sent (target, rays, bytes); and the order in which passes were admitted.

Shards keep the records (a few list appends per step) and hand them back with their poll
replies; the coordinator only appends them here.

A job re-run after a lost shard (a new epoch) numbers each shard's steps from 0 again, and
the records of the run it gave up stay here (their CPU was spent, and the passes that
finished in it are not run again). So `to_dict` numbers each shard's steps on across runs:
a run's steps follow the earlier runs' on every shard, as they did in time (the coordinator
ends one run on every shard before it begins the next), and (shard, step) names one step.
A parcel never crosses runs (a shard drops a parcel of another epoch), so the producers a
step names are renumbered with its own run's offsets.
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
        """{"k", "steps" (by shard, then step), "admitted", "runs"}: each step record as the
        shard made it, with "step" and the inputs' producer steps numbered on across runs,
        and "run" (0: the first) in place of the epoch."""
        epochs = sorted({r.get("epoch", 0) for r in self.steps})
        run_of = {e: i for i, e in enumerate(epochs)}
        # (run, shard) -> its highest step number, recorded or named by a consumer (the
        # records a shard held when its run was given up are gone)
        last: dict[tuple[int, int], int] = {}
        for r in self.steps:
            run = run_of[r.get("epoch", 0)]
            for sh, step in [(r["shard"], r["step"]), *((i[0], i[1]) for i in r["inputs"])]:
                last[(run, sh)] = max(last.get((run, sh), -1), step)
        base: dict[tuple[int, int], int] = {}  # (run, shard) -> steps of the earlier runs
        for sh in range(self.k):
            n = 0
            for run in range(len(epochs)):
                base[(run, sh)] = n
                n += last.get((run, sh), -1) + 1
        steps = []
        for r in self.steps:
            run = run_of[r.get("epoch", 0)]
            rec = {k: v for k, v in r.items() if k != "epoch"}
            rec["run"] = run
            rec["step"] = r["step"] + base[(run, r["shard"])]
            rec["inputs"] = [(src, src_step + base[(run, src)], *rest)
                             for src, src_step, *rest in r["inputs"]]
            steps.append(rec)
        steps.sort(key=lambda r: (r["shard"], r["step"]))
        return {"k": self.k, "steps": steps, "admitted": list(self.admitted),
                "runs": max(len(epochs), 1)}
