"""The shard-side code the driver starts without importing it.

`ShardActor` is what the pool starts as a Ray actor (threaded: `max_concurrency`). It
imports `nprt.workers.wavefront.shard` (Embree, numba, ONNX Runtime) inside the actor's
process, and runs the shard as a mailbox:

- `deliver` (called by other shards, and by the coordinator for camera-ray orders) only
  appends a parcel to the inbox: a few microseconds, on a Ray thread;
- one wavefront thread takes *everything* in the inbox, runs it as one `Shard.step` (any
  passes, any senders), and sends its parcels straight to the target shards' actors
  (`deliver.remote`: the batch travels through the object store as a call argument);
  the coordinator is not on the ray path. A step sends at its end, and also during it
  whenever EMIT_RAYS rays or more are leaving for one shard (which starts on them at once
  if it is waiting).
  A small parcel may wait in the shard's `Outbox` to leave with a later parcel for the
  same target;
- a step whose own rays stay here bounces them again (another iteration) until they end
  or leave; once parcels wait in the inbox, the rays left after an iteration go on in
  the next step instead, with those parcels (`Shard.step`, carry; CARRY_RAYS), so the
  small later bounces share an iteration's fixed cost with the new arrivals;
- the weight of passes whose rays ended here waits until `poll` (a long poll the
  coordinator keeps outstanding) hands it back with the shard's CPU and phase totals.

A job run is an epoch (`begin`): parcels of any other epoch are dropped on arrival, so
after a fault the coordinator starts a new epoch and stale parcels in flight are harmless.
Ray's CPU per parcel (bench/render/bench_ray_calls.py):
- `deliver` returns no object ref (`num_returns=0`): nobody reads a delivery's answer (a
  shard that dies is found by the coordinator's polls), and without one a parcel makes
  no return object to register, reply with and free. Together with task events off
  (`pool.py`), Ray's CPU per 100-ray parcel fell by 0-21 % in three runs.
- Tried and dropped: `deliver` on one thread of its own (a concurrency group of 1), so
  that back-to-back deliveries do not take turns at the GIL on several of the actor's
  threads. It halved Ray's CPU per 100-ray parcel at a load average of about 60, but on
  a quieter machine it cost 0-15 % more (bench_ray_calls variant
  `nprt_one_delivery_thread`, two locked runs).

`build_world` is a Ray task that builds the instance table, whose BVH is built by a
compiled kernel, on a worker: the driver keeps only the reference to it."""

from __future__ import annotations

import ctypes
import functools
import os
import threading
import time
import uuid

import ray

from nprt.workers.runtime.outbox import Outbox
from nprt.workers.runtime.protocol import Parcel, PollReply, sum_credits

MAX_CONCURRENCY = 8  # Ray threads per actor: deliver, poll and collect never wait on a step
SETTLE_S = 30.0  # a settling poll waits at most this long for the step in progress
WAVEFRONT_THREAD = "nprt-wavefront"  # the wavefront thread's OS name (`name_os_thread`)
_PR_SET_NAME = 15  # prctl(2)
# A step's fixed cost (a Ray call per target, per-step glue) is paid per step, its ray work
# per ray: with rays (not orders) for fewer than HOLD_RAYS in the inbox, the wavefront thread
# waits up to HOLD_S for more before stepping (0: step on whatever is there). The coordinator
# hands both to `begin`, so a benchmark sets them in its driver. On 16 cores at K = 8 (city
# and forest, both modes; bench_step_hold, bench/README.md) this hold took 6-11 % off the
# CPU against none (32-41 % fewer steps) at a wall within -0/+8 %, one run each.
HOLD_RAYS = 16384
HOLD_S = 0.008
# A parcel of fewer than SEND_RAYS rays waits, merged with the next steps' parcels for the same
# target, until they carry SEND_RAYS together, the oldest has waited SEND_S, or this shard's
# inbox is empty after a step (nprt.workers.runtime.outbox; the coordinator hands both to
# `begin`): a Ray call costs about the same CPU for 10 rays as for 1,000. On 2 cores at K = 8
# (city and forest, exact and proxy; bench_step_hold --sends, bench/README.md) it took 28-39 %
# of the parcels and -11 to +1 % of the CPU (medians of 3 rounds); a held parcel leaves up
# to a step later, and its effect on the wall on dedicated cores is not measured yet.
SEND_RAYS = 1024
SEND_S = 0.02
# A step sends what is leaving for a shard before it ends, once that is EMIT_RAYS rays or
# more (`Shard.step`, emit; 0: only at the step's end), so that a peer waiting for those rays
# starts on them during the step rather than after it. The coordinator hands it to `begin`.
EMIT_RAYS = 8192
# A step's rays that stay on their shard bounce again in the same step (another iteration of
# the wavefront). Each iteration has a fixed cost (kernel and onnxruntime calls, batch glue),
# and the later ones are small: in one process at K = 8 a step costs 5.6-7.2 ms beyond its
# rays in proxy mode and 2.1-3.3 ms in exact (`bench_visits --step-cap`), and runs about five
# iterations, of median 340, 180 and 90 rays from the third (city). Once parcels wait in the
# shard's inbox, the rays left after an iteration (if fewer than CARRY_RAYS) go on in the
# next step, with those (`carry_when`; 0: never). The coordinator hands it to `begin`. In
# the dedicated-core model at K = 8 (bench/README.md, "A step's last bounces go on in the
# next step"), carrying whatever is left beat carrying under 4,096 rays in proxy mode in 6
# of 6 paired rounds (city, forest, windy) and in exact mode in 2 of 4; 2^20 carries, in
# effect, whatever is left.
CARRY_RAYS = 1 << 20


def carry_when(waiting, carry_rays: int):
    """`Shard.step`'s carry: given the rays left after an iteration, True when they are
    fewer than carry_rays and waiting() (other rays wait for the shard); None for 0."""
    if carry_rays <= 0:
        return None
    return lambda left: left < carry_rays and waiting()


class ShardActor:
    """Drives nprt.workers.wavefront.shard.Shard; tests/distributed/test_driver_imports.py
    checks that the calls the coordinator and pool make exist here."""

    def __init__(self, config):
        """config: ShardConfig. The shard itself is made by `load`, which brings its meshes,
        the world and the proxies: nothing the constructor takes lives in the object store
        (Ray re-runs only the constructor on a restart, and prints an error line for an actor
        whose constructor arguments do; an in-memory scene's meshes do)."""
        self._config = config
        self._shard = None
        self.id = config.shard_id
        self.incarnation = uuid.uuid4().hex  # a restart by Ray makes a new one
        self._cv = threading.Condition()
        self._step_lock = threading.Lock()  # the Shard is run by one thread at a time
        self._inbox: list[Parcel] = []
        self._hold = (0, 0.0)  # (HOLD_RAYS, HOLD_S) of the run
        self._emit_rays = 0  # EMIT_RAYS of the run
        self._carry_rays = 0  # CARRY_RAYS of the run
        self._outbox = Outbox(0)  # the run's small parcels held back (`_run` only)
        self._running = False  # the wavefront thread holds parcels it has not accounted for
        self._epoch: int | None = None
        self._peers: list | None = None
        self._trace = False
        self._error: BaseException | None = None
        self._reset_totals()
        threading.Thread(target=self._loop, name=f"shard{self.id}-wavefront",
                         daemon=True).start()

    def __repr__(self) -> str:  # Ray prefixes the actor's log lines with it
        shard = self.__dict__.get("_shard")
        return repr(shard) if shard is not None else f"Shard({self.__dict__.get('id')}, not loaded)"

    def _reset_totals(self) -> None:
        self._returned: list = []
        self._steps = self._bytes_in = self._bytes_out = 0
        self._parcels_in = self._parcels_out = 0
        self._busy_s = 0.0
        self._wavefront_cpu_s = 0.0  # the wavefront thread's own CPU (not Ray's threads)
        self._phase_s: dict[str, float] = {}
        self._phase_cpu_s: dict[str, float] = {}
        self._records: list[dict] = []
        self._cpu0 = time.process_time()

    # -- the pool ---------------------------------------------------------------------

    def load(self, world, proxies, meshes, all_meshes=None) -> dict:
        """Make the Shard (once: a no-op on a loaded actor); meshes, all_meshes as Shard's.
        Returns `ready()`."""
        if self._shard is None:
            from nprt.workers.wavefront.shard import Shard

            self._shard = Shard(self._config, world, meshes, proxies, all_meshes)
        return self.ready()

    def ready(self) -> dict:
        if self._shard is None:  # restarted by Ray, not loaded again yet
            return {"shard": self.id, "pid": os.getpid(), "loaded": False,
                    "incarnation": self.incarnation}
        return {**self._shard.ready(), "loaded": True, "incarnation": self.incarnation}

    def warm(self) -> float:
        with self._step_lock:
            return self._shard.warm()

    def set_world(self, world) -> int:
        with self._step_lock:
            return self._shard.set_world(world)

    # -- a job --------------------------------------------------------------------------

    def begin(self, epoch: int, settings, peers: list, trace: bool = False,
              hold: tuple[int, float] = (0, 0.0), send: tuple[int, float] = (0, 0.0),
              emit_rays: int = 0, carry_rays: int = 0) -> str:
        """Start job run `epoch`: its settings, the K actor handles to send to (this one
        included), no pass state; hold: (rays, seconds), how long a step may wait for more
        rays (HOLD_RAYS, HOLD_S); send: (rays, seconds), how long a small parcel may wait
        for more (SEND_RAYS, SEND_S); emit_rays: rays leaving that a step sends before it
        ends (EMIT_RAYS; 0: none); carry_rays: fewer rays left after an iteration go on in
        the next step when parcels wait (CARRY_RAYS; 0: never). Returns the incarnation."""
        with self._cv:
            self._epoch, self._peers, self._trace = epoch, peers, trace
            self._hold, self._emit_rays = hold, int(emit_rays)
            self._carry_rays = int(carry_rays)
            # A new object: a step of the last run still in flight keeps the old one.
            self._outbox = Outbox(len(peers), *send)
            self._inbox.clear()
            self._error = None
            self._reset_totals()
        with self._step_lock:
            self._shard.begin(settings)
        return self.incarnation

    def end(self, epoch: int) -> PollReply | None:
        """Drop run `epoch` (finished, canceled or failed): its parcels and pass state.
        Returns the run's final totals and the trace records no poll handed back (None:
        not this run). A step still running is dropped uncounted (`_run`), so the totals
        and the records count the same steps: a run given up keeps a trace that adds up."""
        with self._cv:
            if self._epoch != epoch:
                return None
            self._epoch = None
            self._inbox.clear()
            records, self._records = self._records, []
            final = self._reply(epoch, [], records)
            self._cv.notify_all()  # a long poll of the run answers now, not at its timeout
        if self._shard is not None:  # a restarted actor not loaded again holds nothing
            with self._step_lock:
                self._shard.reset()
        return final

    @ray.method(num_returns=0)
    def deliver(self, parcel: Parcel) -> None:
        with self._cv:
            if parcel.epoch != self._epoch:
                return  # a parcel of a dropped run
            self._inbox.append(parcel)
            self._cv.notify_all()

    def poll(self, epoch: int, timeout_s: float, settle: bool = False,
             collect: tuple[int, ...] = ()) -> PollReply:
        """Wait up to timeout_s for weight to hand back; then the totals so far. settle:
        first wait for the step in progress to finish its accounting (the job's last poll:
        a step sends its parcels before it records itself, so a pass can complete on
        another shard while this one has yet to add the step's totals and trace record).
        collect: finished passes whose films to hand back in the reply (as `collect`
        gives them): the coordinator's collect rides on the long poll, one call instead
        of two (coordinator.COLLECT_ON_POLL_FROM_K)."""
        with self._cv:
            if settle:
                self._cv.wait_for(lambda: not (self._running or self._inbox)
                                  or self._error is not None or self._epoch != epoch,
                                  timeout=SETTLE_S)
            self._cv.wait_for(lambda: self._returned or self._error is not None
                              or self._epoch != epoch, timeout=timeout_s)
            if self._error is not None:
                raise RuntimeError(f"shard {self.id} failed in its wavefront") from self._error
            returned, records = [], []
            # A long poll of an earlier run (the coordinator drops it when a frame or run
            # ends) can wake after the next `begin`: the weight and trace records are the
            # new run's, and taking them would lose them (the pass never completes). So can
            # a long poll of this run that times out once the job is done: its trace
            # records go with a poll the coordinator reads for sure, one that hands back
            # weight (a pass cannot complete without it), collects or settles.
            if self._epoch == epoch:
                returned, self._returned = self._returned, []
                if returned or settle or collect:
                    records, self._records = self._records, []
            reply = self._reply(self._epoch, returned, records)
        if collect:
            reply.collected = self.collect(epoch, list(collect))[1]
        return reply

    def _reply(self, epoch: int | None, returned: list, records: list) -> PollReply:
        """The totals so far of the run, with this weight and these trace records (called
        with self._cv held)."""
        return PollReply(
            self.id, self.incarnation, epoch, returned, steps=self._steps,
            busy_s=self._busy_s, cpu_s=time.process_time() - self._cpu0,
            wavefront_cpu_s=self._wavefront_cpu_s,
            phase_s=dict(self._phase_s), phase_cpu_s=dict(self._phase_cpu_s),
            bytes_in=self._bytes_in, bytes_out=self._bytes_out,
            parcels_in=self._parcels_in, parcels_out=self._parcels_out, trace=records,
            idle=not (self._running or self._inbox), at=time.monotonic())

    def collect(self, epoch: int, indices: list[int]) -> tuple[str, list]:
        """(incarnation, [(pass index, sums or None, stats dict or None)]) of finished
        passes. A finished pass has no ray left anywhere, so no step touches its state."""
        if epoch != self._epoch:
            return self.incarnation, [(i, None, None) for i in indices]
        return self.incarnation, self._shard.collect(indices)

    # -- the wavefront thread -----------------------------------------------------------

    def _held_enough(self, epoch: int | None) -> bool:
        """Whether a holding wavefront thread steps now (with self._cv held): rays enough,
        orders (camera rays come in passes: already a big batch), rays carried from the last
        step (they would have run in it: a carry regroups rays, it never makes them wait),
        or the run ended."""
        return (self._epoch != epoch or any(p.orders for p in self._inbox)
                or (self._shard is not None and self._shard.carried_rays > 0)
                or sum(p.n_rays for p in self._inbox) >= self._hold[0])

    def _loop(self) -> None:
        name_os_thread(WAVEFRONT_THREAD)
        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._inbox))
                if self._hold[1] > 0:
                    self._cv.wait_for(functools.partial(self._held_enough, self._epoch),
                                      timeout=self._hold[1])
                parcels, self._inbox = self._inbox, []
                if not parcels:  # the run ended while this thread held
                    continue
                epoch, peers, trace = self._epoch, self._peers, self._trace
                outbox, emit_rays = self._outbox, self._emit_rays
                self._running = True
            try:
                self._run(epoch, peers, trace, outbox, emit_rays, parcels)
            except BaseException as e:  # handed to the coordinator by the next poll
                with self._cv:
                    self._error = e
            finally:
                with self._cv:
                    self._running = False
                    self._cv.notify_all()

    def _run(self, epoch: int, peers: list, trace: bool, outbox: Outbox, emit_rays: int,
             parcels: list[Parcel]) -> None:
        # The wall clock first: a parcel sent `at` seconds after t0 then leaves no earlier
        # than start + at (the trace's bound, tests/deploy/test_trace.py), even where this
        # thread is preempted between the two reads.
        start = time.time()
        t0, c0 = time.perf_counter(), time.thread_time()
        orders = [o for p in parcels for o in p.orders]
        credits = sum_credits(p.credits for p in parcels)
        rays = [p for p in parcels if p.n_rays]
        step_id = self._steps
        # (target, rays, bytes, seconds into the step when it left; None: at its end)
        sent = []

        def send(out_parcels: list, flush: bool, early: bool) -> None:
            at = time.perf_counter() - t0 if early else None
            for target, out in outbox.put(out_parcels, time.monotonic(), flush):
                out.epoch, out.source = epoch, (self.id, step_id, at)
                peers[target].deliver.remote(out)
                sent.append((target, out.n_rays, out.nbytes, at))

        emit = functools.partial(send, flush=False, early=True) if emit_rays else None
        carry = carry_when(lambda: bool(self._inbox), self._carry_rays)
        with self._step_lock:
            res = self._shard.step(orders, rays, credits, emit, emit_rays, carry)
        end = time.time()  # before the step's last parcels leave
        with res.times.phase("send"):
            with self._cv:  # nothing left to do: held parcels leave too (outbox.py)
                flush = not self._inbox
            send(res.parcels, flush, False)
        with self._cv:
            if self._epoch != epoch:
                return  # dropped while this step ran: its weight is stale
            self._returned += res.returned.items()
            self._steps += 1
            self._busy_s += time.perf_counter() - t0
            self._wavefront_cpu_s += time.thread_time() - c0
            self._bytes_in += res.bytes_in
            self._bytes_out += sum(b for _, _, b, _ in sent)
            self._parcels_in += len(parcels)
            self._parcels_out += len(sent)
            for name, v in res.times.phase_s.items():
                self._phase_s[name] = self._phase_s.get(name, 0.0) + v
            for name, v in res.times.phase_cpu_s.items():
                self._phase_cpu_s[name] = self._phase_cpu_s.get(name, 0.0) + v
            if trace:
                self._records.append({
                    "shard": self.id, "step": step_id, "epoch": epoch, "start": start,
                    "end": end,
                    "cpu_s": sum(res.times.phase_cpu_s.values()),
                    "busy_s": time.perf_counter() - t0,
                    "orders": [p.index for p in orders], "passes": sorted(credits),
                    "inputs": [(*p.source[:2], p.n_rays, p.nbytes, p.source[2]) for p in rays
                               if p.source is not None],
                    "outputs": sent})
            if res.returned:
                self._cv.notify_all()


def name_os_thread(name: str) -> None:
    """Give the calling thread an OS name (Linux; at most 15 bytes kept), which `top -H`,
    /proc/<pid>/task/<tid>/comm and bench/render/bench_shard_threads.py show. Python 3.11
    names threads for Python alone. Elsewhere, or if prctl is missing: nothing."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):
        pass


@ray.remote(num_cpus=0)  # a moment's work: it must not wait for CPUs the shards reserve
def build_world(meta, owner):
    """nprt.workers.wavefront.world.ShardWorld.build(meta, owner), run on a worker."""
    from nprt.workers.wavefront.world import ShardWorld

    return ShardWorld.build(meta, owner)
