"""A trace-driven model of a render on K dedicated nodes joined by links of bandwidth B: a
small discrete-event simulation that replays the shard calls a Coordinator recorded
(workers/runtime/calltrace.py) with their compute times, the bytes of every parcel and which calls
consumed it.

What it models, following workers/runtime/coordinator.py:
- Shard s runs on node s; its calls run one at a time, in the recorded order (a Ray actor
  runs its calls in submission order; a call whose parcels are still on the wire blocks
  the calls behind it).
- The coordinator dispatches a call once every call whose output it consumes has returned,
  with at most MAX_QUEUED_CALLS calls of one shard in flight, and with a pass attempt
  (token) admitted only while fewer than `window` attempts are live. A message between the
  coordinator and a shard takes `rpc_s` each way (its processing included).
- A parcel moves once its consumer's call reaches the consumer's node (Ray pulls the
  arguments of a queued actor call). Every node has an uplink and a downlink of B; flows
  share them max-min fairly (TCP-like), so a parcel between two nodes is limited by the
  busier of the sender's uplink and the receiver's downlink.
- A pass ends when each shard, after the calls queued before it, has handed back its
  partial film (n_pixels x 3 float64) over its uplink to the coordinator's node.

What it does not model: the grouping of parcels into calls changes with timing in a real
run, and the replay keeps the recorded grouping; and CPU contention between nodes (the
model's nodes are dedicated: pass compute times measured without contention, or corrected
for it).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from nprt.workers.runtime.coordinator import MAX_QUEUED_CALLS

HEAD = -1  # the coordinator's node: its own link is not a bottleneck (unshaped)


@dataclass
class _Flow:
    src: int
    dst: int
    left: float  # bytes still to move
    done: object  # callback(time)
    rate: float = 0.0


@dataclass
class _Job:
    """A work call or a collect, queued on one shard."""

    kind: str  # "work" | "collect"
    index: int  # call number, or token
    arrive_s: float
    waiting: int = 0  # parcels still on the wire
    cpu_s: float = 0.0


@dataclass
class Replay:
    """makespan_s: from the first dispatch to the last pass's film at the coordinator."""

    makespan_s: float
    call_start_s: np.ndarray
    call_end_s: np.ndarray
    busy_s: np.ndarray  # (k,) compute seconds per node
    bytes_moved: int
    extra: dict = field(default_factory=dict)


class _Network:
    """Max-min fair sharing of per-node uplinks and downlinks of `bps` bytes per second."""

    def __init__(self, bytes_per_s: float):
        self.cap = bytes_per_s
        self.flows: list[_Flow] = []

    def add(self, flow: _Flow) -> None:
        self.flows.append(flow)
        self._rates()

    def _rates(self) -> None:
        """Progressive filling over the links each flow uses (the head's link is free)."""
        links: dict[tuple, list[_Flow]] = {}
        for f in self.flows:
            f.rate = -1.0
            for link in (("up", f.src), ("down", f.dst)):
                if link[1] != HEAD:
                    links.setdefault(link, []).append(f)
        left = {link: self.cap for link in links}
        while True:
            open_links = {lk: [f for f in fs if f.rate < 0] for lk, fs in links.items()}
            open_links = {lk: fs for lk, fs in open_links.items() if fs}
            if not open_links:
                break
            bottleneck = min(open_links, key=lambda lk: left[lk] / len(open_links[lk]))
            share = left[bottleneck] / len(open_links[bottleneck])
            for f in open_links[bottleneck]:
                f.rate = share
                for link in (("up", f.src), ("down", f.dst)):
                    if link in left:
                        left[link] -= share
        for f in self.flows:
            if f.rate < 0:  # between two unshaped ends: instant
                f.rate = float("inf")

    def next_done(self, now: float) -> float:
        return min((now + f.left / f.rate for f in self.flows), default=float("inf"))

    def advance(self, now: float, to: float) -> list[_Flow]:
        """Move every flow on to time `to`; returns (and drops) the flows that finished."""
        dt = to - now
        done = []
        for f in self.flows:
            f.left -= f.rate * dt if np.isfinite(f.rate) else f.left
            if f.left <= 1e-6 * max(1.0, self.cap):
                done.append(f)
        if done:
            self.flows = [f for f in self.flows if f not in done]
            self._rates()
        return done


def replay(trace: dict, bandwidth_bps: float, rpc_s: float, window: int,
           film_bytes: dict[int, int] | None = None, cpu_s: np.ndarray | None = None) -> Replay:
    """Replay `trace` (TraceRecorder.to_dict()) on its K shards' dedicated nodes.

    bandwidth_bps: each node's link, bits per second, each direction; rpc_s: one way,
    coordinator to shard or back; window: pass attempts in flight (Coordinator.window);
    film_bytes: token -> bytes of one shard's partial film (default none); cpu_s: (n_calls,)
    compute time per call (default: the recorded busy_s)."""
    k = trace["k"]
    calls = trace["calls"]
    n = len(calls)
    cpu = np.array([c["busy_s"] for c in calls]) if cpu_s is None else np.asarray(cpu_s)
    film_bytes = film_bytes or {}
    net = _Network(bandwidth_bps / 8.0)
    by_shard = [[c["call"] for c in calls if c["shard"] == s] for s in range(k)]
    pos = [0] * k  # next call of each shard to dispatch
    returned = np.full(n, np.inf)
    start, end = np.full(n, np.nan), np.full(n, np.nan)
    token_calls: dict[int, int] = {}  # token -> its calls not yet returned
    first_seen: dict[int, int] = {}  # token -> the first call carrying it
    for c in calls:
        for t in c["tokens"]:
            token_calls[t] = token_calls.get(t, 0) + 1
            first_seen.setdefault(t, c["call"])
    order = sorted(first_seen)  # tokens in admission order
    admit_rank = {t: i for i, t in enumerate(order)}
    completions: list[float] = []  # times at which tokens finished (film at the head)
    queues: list[list[_Job]] = [[] for _ in range(k)]
    running: list[_Job | None] = [None] * k
    in_flight = [0] * k
    films_left: dict[int, int] = {}
    events: list[tuple[float, int, str, tuple]] = []  # (time, seq, what, args)
    seq = [0]
    busy = np.zeros(k)
    moved = [0]

    def at(t: float, what: str, *args) -> None:
        seq[0] += 1
        heapq.heappush(events, (t, seq[0], what, args))

    def admitted(token: int) -> float:
        """When the coordinator could admit this token: within the window."""
        r = admit_rank[token]
        if r < window:
            return 0.0
        if len(completions) < r - window + 1:
            return np.inf
        return sorted(completions)[r - window]

    def try_dispatch(now: float) -> None:
        for s in range(k):
            while pos[s] < len(by_shard[s]) and in_flight[s] < MAX_QUEUED_CALLS:
                c = calls[by_shard[s][pos[s]]]
                ready = max([returned[p] for p, _ in c["inputs"]] +
                            [admitted(t) for t in c["tokens"] if first_seen[t] == c["call"]] +
                            [0.0])
                if ready > now:
                    break
                pos[s] += 1
                in_flight[s] += 1
                at(now + rpc_s, "arrive", c["call"])

    def try_run(s: int, now: float) -> None:
        if running[s] is not None or not queues[s]:
            return
        job = queues[s][0]
        if job.waiting or job.arrive_s > now:
            return
        queues[s].pop(0)
        running[s] = job
        if job.kind == "work":
            start[job.index] = now
        at(now + job.cpu_s, "end", s)

    def parcel_done(call: int, s: int):
        def done(now: float) -> None:
            job = next(j for j in queues[s] if j.kind == "work" and j.index == call)
            job.waiting -= 1
            try_run(s, now)
        return done

    def film_done(token: int):
        def done(now: float) -> None:
            films_left[token] -= 1
            if films_left[token] == 0:
                completions.append(now + rpc_s)
                at(now + rpc_s, "admit")
        return done

    now = 0.0
    try_dispatch(now)
    while events or net.flows:
        t_event = events[0][0] if events else np.inf
        t_flow = net.next_done(now)
        if t_flow < t_event:
            for f in net.advance(now, t_flow):
                f.done(t_flow)
            now = t_flow
            continue
        for f in net.advance(now, t_event):
            f.done(t_event)
        now, _, what, args = heapq.heappop(events)
        if what == "arrive":
            c = calls[args[0]]
            s = c["shard"]
            job = _Job("work", c["call"], now, cpu_s=float(cpu[c["call"]]))
            queues[s].append(job)
            for (p, _), nbytes in zip(c["inputs"], c["input_bytes"], strict=True):
                src = calls[p]["shard"]
                if src == s or nbytes == 0:
                    continue
                job.waiting += 1
                moved[0] += nbytes
                net.add(_Flow(src, s, float(nbytes), parcel_done(c["call"], s)))
            try_run(s, now)
        elif what == "collect":
            s, token = args
            queues[s].append(_Job("collect", token, now))
            try_run(s, now)
        elif what == "end":
            s = args[0]
            job, running[s] = running[s], None
            busy[s] += job.cpu_s
            if job.kind == "work":
                end[job.index] = now
                at(now + rpc_s, "return", job.index)
            else:
                nbytes = film_bytes.get(job.index, 0)
                moved[0] += nbytes
                net.add(_Flow(s, HEAD, float(max(nbytes, 1)), film_done(job.index)))
            try_run(s, now)
        elif what == "return":
            c = calls[args[0]]
            returned[c["call"]] = now
            in_flight[c["shard"]] -= 1
            for t in c["tokens"]:
                token_calls[t] -= 1
                if token_calls[t] == 0:  # the coordinator collects the pass from every shard
                    films_left[t] = k
                    for s in range(k):
                        at(now + rpc_s, "collect", s, t)
            try_dispatch(now)
        elif what == "admit":
            try_dispatch(now)
    if not np.isfinite(returned).all():
        raise RuntimeError("replay stalled: some calls never ran (inconsistent trace)")
    return Replay(float(max(completions)), start, end, busy, int(moved[0]))


def cpu_corrected(trace: dict, cpu_over_busy: list[float]) -> np.ndarray:
    """Per-call compute time on a dedicated node: busy_s scaled by its shard's measured
    process CPU seconds over busy seconds (busy time on a shared host includes waiting
    for a core)."""
    return np.array([c["busy_s"] * min(1.0, cpu_over_busy[c["shard"]])
                     for c in trace["calls"]])


RPC_GRID_S = np.geomspace(1e-4, 0.5, 60)


def fit_rpc_s(runs: list[tuple[dict, float, float, int, dict]],
              grid=RPC_GRID_S) -> tuple[float, float]:
    """The one-way coordinator latency that best explains measured walls: runs are (trace,
    bandwidth_bps, measured wall s, window, film_bytes). Returns (rpc_s, mean |log error|)."""
    best = None
    for rpc in grid:
        err = np.mean([abs(np.log(replay(tr, bw, rpc, w, fb).makespan_s / wall))
                       for tr, bw, wall, w, fb in runs])
        if best is None or err < best[1]:
            best = (float(rpc), float(err))
    return best
