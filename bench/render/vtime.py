"""K in-process Shards run as if each had a dedicated core: a discrete-event simulation in
virtual time whose steps are real `Shard.step` calls, each lasting the process CPU it took
here plus Ray's CPU for the parcels it sent and received (bench/render/raycalls.py).

Unlike a replay of recorded steps (bench/network/netmodel.py), which keeps the grouping of
rays into steps that the recording happened to have, this regroups them as they would
arrive on dedicated cores: a shard that is free steps on everything that has reached it by
then, in virtual time. The rules, following workers/runtime/coordinator.py and remote.py:
- the coordinator orders up to `window` passes at once (one live pass a tile), each from
  shard `index % K`; an order reaches its shard `rpc_s` after it is made;
- a shard runs one step at a time, starting when it is free and something has arrived;
  holding (`hold`: `remote.HOLD_RAYS`, `HOLD_S`), it waits for rays enough or an order,
  at most HOLD_S;
- a parcel leaves at the step's end, or, with `emit_rays`, where it left during the step
  (its CPU offset into the step), and arrives `rpc_s` plus its bytes over `link_bps`
  later; with `send` (`remote.SEND_RAYS`, `SEND_S`) it goes through the runtime's own
  `Outbox` first, on the virtual clock: a small one waits for the next parcels to its
  target, and everything held leaves when nothing has reached the shard by a step's end;
- with `carry_rays`, a step leaves what it has left after an iteration to the shard's next
  step once a parcel has reached the shard, in virtual time, and a shard with carried rays
  steps without holding (`Shard.step`, `remote.carry_when`);
- a pass is done once its weight is back (`rpc_s` after the step that returns the last of
  it ends); the next pass is ordered then (films are collected at once, outside the
  clock).

What it leaves out: Ray's threads run beside the step on the same core (their CPU is added
to it), and the coordinator has a core of its own. Every step runs in this one thread, so
its CPU is exact.
"""

from __future__ import annotations

import heapq
import time
from fractions import Fraction

import numpy as np

from nprt.workers.filmsum import FilmSums
from nprt.workers.passes import count_tiles, iter_passes, pass_at
from nprt.workers.runtime.coordinator import live_window
from nprt.workers.runtime.outbox import Outbox
from nprt.workers.runtime.protocol import sum_credits
from nprt.workers.runtime.remote import carry_when
from nprt.workers.settings import RenderSettings


def simulate(shards: list, s: RenderSettings, cost: dict, rpc_s: float, link_bps: float,
             emit_rays: int = 0, hold: tuple[int, float] = (0, 0.0),
             send: tuple[int, float] = (0, 0.0), carry_rays: int = 0) -> dict:
    """Render every pass of s on the in-process shards in virtual time. cost: Ray's CPU per
    parcel (`raycalls.parcel_cost`); emit_rays: `remote.EMIT_RAYS`; hold: (rays, seconds),
    `remote.HOLD_RAYS` and `HOLD_S` (0 seconds: no hold); send: (rays, seconds),
    `remote.SEND_RAYS` and `SEND_S` (0 rays: every parcel leaves at once); carry_rays:
    `remote.CARRY_RAYS` (fewer rays left after an iteration go on in the next step once a
    parcel has reached the shard, in virtual time; 0: never). Returns
    {"wall_s": virtual render wall, "busy_s": (K,) virtual seconds each shard stepped,
    "steps", "parcels", "early_parcels", "film": (h * w, 3) float64}."""
    k, tiles = len(shards), count_tiles(s)
    window = live_window(k, tiles)
    for sh in shards:
        sh.begin(s)
    waiting = list(iter_passes(s))
    live: dict[int, Fraction] = {}
    # per shard: heap of (arrival time, sequence, orders, parcel or None, credits)
    inbox: list[list] = [[] for _ in range(k)]
    free_at = np.zeros(k)
    busy = np.zeros(k)
    film = np.zeros((s.height * s.width, 3))
    seq = [0]
    counts = {"steps": 0, "parcels": 0, "early_parcels": 0}
    outbox = [Outbox(k, *send) for _ in range(k)]
    done_at = 0.0

    def arrive(target: int, t: float, orders=(), parcel=None, credits=None) -> None:
        seq[0] += 1
        heapq.heappush(inbox[target], (t, seq[0], tuple(orders), parcel, credits or {}))

    def admit(t: float) -> None:
        live_tiles = {i % tiles for i in live}
        for p in list(waiting):
            if len(live) >= window:
                break
            if p.index % tiles in live_tiles:
                continue
            waiting.remove(p)
            live_tiles.add(p.index % tiles)
            live[p.index] = Fraction(0)
            arrive(p.index % k, t + rpc_s, (p,), None, {p.index: Fraction(1)})

    def wire(nbytes: int) -> float:
        return rpc_s + 8.0 * nbytes / link_bps

    def send_cost(nbytes: int) -> float:
        return cost["send_s"] + cost["send_s_per_byte"] * nbytes

    def start_of(i: int) -> float:
        """When shard i steps next on what is known to reach it. Every other shard starts
        no earlier (the loop takes the earliest), so nothing sent later arrives before."""
        t0 = max(free_at[i], inbox[i][0][0])
        if hold[1] <= 0 or shards[i].carried_rays:  # carried rays do not wait (remote.py)
            return t0
        rays = 0
        for t, _, orders, parcel, _ in sorted(inbox[i]):
            if t > t0 + hold[1]:
                break
            rays += 0 if parcel is None else parcel.n_rays
            if orders or rays >= hold[0]:
                return max(t0, t)
        return t0 + hold[1]

    admit(0.0)
    while live or waiting:
        ready = [(start_of(i), i) for i in range(k) if inbox[i]]
        if not ready:
            raise RuntimeError("simulation stalled: passes live and nothing in flight")
        start, sid = min(ready)
        items = []
        while inbox[sid] and inbox[sid][0][0] <= start:
            items.append(heapq.heappop(inbox[sid]))
        orders = [o for it in items for o in it[2]]
        parcels = [it[3] for it in items if it[3] is not None]
        credits = sum_credits(it[4] for it in items)
        recv = sum(cost["receive_s"] + cost["receive_s_per_byte"] * p.nbytes for p in parcels)
        early: list = []  # (CPU offset into the step, (k,) parcels)
        c0 = time.process_time()

        def emitted(out, c0=c0, early=early):
            early.append((time.process_time() - c0, out))

        def waits(c0=c0, sid=sid, at=start + recv) -> bool:
            """Whether a parcel reached the shard by now, into the step (its carry)."""
            now = at + time.process_time() - c0
            return any(it[0] <= now for it in inbox[sid])

        res = shards[sid].step(orders, parcels, credits, emitted if emit_rays else None,
                               emit_rays, carry_when(waits, carry_rays))
        cpu = time.process_time() - c0
        sent_cpu = 0.0
        for offset, out in early:  # each leaves where it was made, after earlier sends
            for target, p in outbox[sid].put(out, start + recv + offset + sent_cpu, False):
                sent_cpu += send_cost(p.nbytes)
                arrive(target, start + recv + offset + sent_cpu + wire(p.nbytes),
                       parcel=p, credits=p.credits)
                counts["early_parcels"] += 1
                counts["parcels"] += 1
        end = start + recv + cpu + sent_cpu
        # As the runtime: held parcels all leave when nothing reached the shard meanwhile.
        flush = not any(it[0] <= end for it in inbox[sid])
        for target, p in outbox[sid].put(res.parcels, end, flush):
            end += send_cost(p.nbytes)
            arrive(target, end + wire(p.nbytes), parcel=p, credits=p.credits)
            counts["parcels"] += 1
        counts["steps"] += 1
        busy[sid] += end - start
        free_at[sid] = end
        back = end + rpc_s
        finished = False
        for i, w in res.returned.items():
            live[i] += w
            if live[i] == 1:
                del live[i]
                collect_pass(shards, s, i, film)
                finished = True
                done_at = max(done_at, back)
        if finished:
            admit(back)
    return {"wall_s": done_at, "busy_s": busy, "film": film, **counts}


def collect_pass(shards: list, s: RenderSettings, index: int, film: np.ndarray,
                 counters: dict | None = None) -> None:
    """Pass `index`'s film from every in-process shard, added to film (h * w, 3) float64;
    its statistics counters added to counters (name -> count) where given."""
    p = pass_at(s, index)
    total = FilmSums.zeros(p.n_pixels)
    for sh in shards:
        for _, sums, st in sh.collect([index]):
            if sums is not None:
                total += sums
            if counters is not None:
                for name, v in (st or {}).get("counters", {}).items():
                    counters[name] = counters.get(name, 0) + v
    film[p.pixels(s.width)] += total.to_float()
