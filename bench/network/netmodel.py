"""A trace-driven model of a render on K dedicated nodes joined by links of bandwidth B: a
small discrete-event simulation that replays the wavefront steps the shards recorded
(workers/runtime/calltrace.py) with their compute times, the bytes of every parcel and which
step consumed it.

What it models, following workers/runtime/coordinator.py and remote.py:
- Shard s runs on node s; its steps run one at a time, in the recorded order. A step starts
  once the shard is free, every parcel it consumed has arrived, and every camera-ray order
  it ran has arrived.
- A parcel leaves when its producing step ends, or as far into it as it was recorded to
  leave (a step sends what is leaving before it ends, `remote.EMIT_RAYS`: the fraction of
  the recorded step is kept, scaled to the step's modelled compute time), and goes straight
  to its consumer's node (shard to shard; no coordinator hop). Every node has an uplink
  and a downlink of B; flows share them max-min fairly (TCP-like).
- The coordinator admits passes in the recorded order, at most `window` live; an order
  reaches its shard `rpc_s` after admission. A pass is complete once every step that ran
  it has ended; the weight reaches the coordinator `rpc_s` later, the collect another
  `rpc_s`, and then every shard sends its film (n_pixels x 3 float64) over its uplink.
- A job re-run after a lost shard: the given-up run's steps first on every shard, then the
  new run's (`StepTrace.to_dict` numbers them on); a re-run pass is admitted once, and
  completes when its steps in both runs have ended.

What it does not model: the grouping of parcels into steps changes with timing in a real
run, and the replay keeps the recorded grouping; CPU contention between nodes (the
model's nodes are dedicated: step compute times measured without contention, or corrected
for it); and films riding on a shard's next poll (coordinator.COLLECT_ON_POLL_FROM_K): the model
collects them at once, a little earlier than the runtime does in mid-job.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from nprt.workers.passes import iter_passes

HEAD = -1  # the coordinator's node: its own link is not a bottleneck (unshaped)


def film_bytes(s) -> dict[int, int]:
    """Token -> bytes of one shard's partial film of that pass, for RenderSettings s (tokens
    follow pass order when nothing is retried)."""
    return {p.index: p.n_pixels * 3 * 2 * 8 for p in iter_passes(s)}  # FilmSums: 2 int64 words


@dataclass
class _Flow:
    src: int
    dst: int
    left: float  # bytes still to move
    done: object  # callback(time)
    rate: float = 0.0


@dataclass
class Replay:
    """makespan_s: from the first admission to the last pass's film at the coordinator;
    step_start_s / step_end_s: (n_steps,) in the trace's step order."""

    makespan_s: float
    step_start_s: np.ndarray
    step_end_s: np.ndarray
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
           film_bytes: dict | None = None, cpu_s: np.ndarray | None = None) -> Replay:
    """Replay `trace` (StepTrace.to_dict()) on its K shards' dedicated nodes.

    bandwidth_bps: each node's link, bits per second, each direction; rpc_s: one way,
    coordinator to shard or back; window: passes live at once (Coordinator.window);
    film_bytes: pass index (int or str) -> bytes of one shard's film (default none);
    cpu_s: (n_steps,) compute time per step (default: the recorded busy_s)."""
    k, steps = trace["k"], trace["steps"]
    n = len(steps)
    cpu = np.array([s["busy_s"] for s in steps]) if cpu_s is None else np.asarray(cpu_s)
    films = {int(i): b for i, b in (film_bytes or {}).items()}
    index = {(s["shard"], s["step"]): i for i, s in enumerate(steps)}
    by_shard = [[i for i, s in enumerate(steps) if s["shard"] == sh] for sh in range(k)]
    waiting = np.zeros(n, np.int64)  # parcels and orders a step still waits for
    # producer step -> [(consumer, bytes)] of the parcels that left at its end, and
    # [(fraction of the step, consumer, bytes)] of those that left before it ended
    consumers: dict[int, list[tuple[int, int]]] = {}
    early: dict[int, list[tuple[float, int, int]]] = {}
    order_step: dict[int, list[int]] = {}  # pass -> steps that generated it
    steps_of: dict[int, int] = {}  # pass -> steps that ran it, not yet ended
    for i, s in enumerate(steps):
        # (src, src_step, rays, bytes[, seconds into the producing step when it left, None
        # or absent: at its end])
        for src, src_step, _rays, nbytes, *left in s["inputs"]:
            j = index.get((src, src_step))
            if j is None:
                continue
            waiting[i] += 1
            busy_j = float(steps[j]["busy_s"])
            if left and left[0] is not None and busy_j > 0:
                frac = min(1.0, float(left[0]) / busy_j)
                early.setdefault(j, []).append((frac, i, int(nbytes)))
            else:
                consumers.setdefault(j, []).append((i, int(nbytes)))
        for p in s["orders"]:
            order_step.setdefault(p, []).append(i)
            waiting[i] += 1
        for p in s["passes"]:
            steps_of[p] = steps_of.get(p, 0) + 1
    admitted = [p for p in dict.fromkeys(trace["admitted"]) if p in steps_of]
    net = _Network(bandwidth_bps / 8.0)
    events: list[tuple[float, int, str, tuple]] = []
    seq = [0]
    start, end = np.full(n, np.nan), np.full(n, np.nan)
    pos, running = [0] * k, [False] * k
    busy = np.zeros(k)
    moved = [0]
    completions: list[float] = []
    films_left: dict[int, int] = {}
    next_admit = [0]

    def at(t: float, what: str, *args) -> None:
        seq[0] += 1
        heapq.heappush(events, (t, seq[0], what, args))

    def admit(now: float, count: int) -> None:
        for _ in range(count):
            if next_admit[0] < len(admitted):
                p = admitted[next_admit[0]]
                next_admit[0] += 1
                for i in order_step.get(p, []):
                    at(now + rpc_s, "arrive", i)

    def try_run(sh: int, now: float) -> None:
        if running[sh] or pos[sh] >= len(by_shard[sh]):
            return
        i = by_shard[sh][pos[sh]]
        if waiting[i]:
            return
        pos[sh] += 1
        running[sh] = True
        start[i] = now
        for frac, j, nbytes in early.get(i, []):
            at(now + frac * float(cpu[i]), "send", i, j, nbytes)
        at(now + float(cpu[i]), "end", i)

    def arrived(i: int):
        def done(now: float) -> None:
            waiting[i] -= 1
            try_run(steps[i]["shard"], now)
        return done

    def send(sh: int, j: int, nbytes: int, now: float) -> None:
        """A parcel from shard sh to step j leaves now."""
        if steps[j]["shard"] == sh or nbytes == 0:
            arrived(j)(now)
            return
        moved[0] += nbytes
        net.add(_Flow(sh, steps[j]["shard"], float(nbytes), arrived(j)))

    def film_done(p: int):
        def done(now: float) -> None:
            films_left[p] -= 1
            if films_left[p] == 0:
                completions.append(now + rpc_s)
                at(now + rpc_s, "admit")
        return done

    admit(0.0, window)
    now = 0.0
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
            arrived(args[0])(now)
        elif what == "end":
            i = args[0]
            sh = steps[i]["shard"]
            running[sh] = False
            end[i] = now
            busy[sh] += float(cpu[i])
            for j, nbytes in consumers.get(i, []):
                send(sh, j, nbytes, now)
            for p in steps[i]["passes"]:
                steps_of[p] -= 1
                if steps_of[p] == 0:  # weight back, then the collect, then K films
                    at(now + 2 * rpc_s, "collect", p)
            try_run(sh, now)
        elif what == "send":
            i, j, nbytes = args
            send(steps[i]["shard"], j, nbytes, now)
        elif what == "collect":
            p = args[0]
            films_left[p] = k
            for sh in range(k):
                nbytes = films.get(p, 0)
                moved[0] += nbytes
                net.add(_Flow(sh, HEAD, float(max(nbytes, 1)), film_done(p)))
        elif what == "admit":
            admit(now, 1)
    if np.isnan(end).any():
        # Name the first steps left, so that a trace that stalls once can be read back.
        left = [f"shard {steps[i]['shard']} step {steps[i]['step']} (waiting for "
                f"{waiting[i]} parcels or orders, started: {not np.isnan(start[i])})"
                for i in np.flatnonzero(np.isnan(end))[:4]]
        raise RuntimeError(f"replay stalled: {int(np.isnan(end).sum())} of {n} steps never "
                           f"ran (inconsistent trace), first {'; '.join(left)}; admitted "
                           f"{next_admit[0]} of {len(admitted)} passes")
    return Replay(float(max(completions, default=0.0)), start, end, busy, int(moved[0]))


def cpu_corrected(trace: dict, cpu_over_busy: list[float]) -> np.ndarray:
    """Per-step compute time on a dedicated node: busy_s scaled by its shard's measured
    process CPU seconds over busy seconds (busy time on a shared host includes waiting
    for a core)."""
    return np.array([s["busy_s"] * min(1.0, cpu_over_busy[s["shard"]])
                     for s in trace["steps"]])


def step_cpu(trace: dict) -> np.ndarray:
    """(n_steps,) compute time per step on a dedicated node: the step's own process CPU
    seconds (its named phases) where it had less than its busy seconds (the rest was
    waiting for a core on a shared host), else its busy seconds (threads in parallel)."""
    return np.array([min(s["busy_s"], s["cpu_s"]) for s in trace["steps"]])


def is_step_trace(trace: dict) -> bool:
    """Whether `trace` is a StepTrace.to_dict() (the earlier runtime recorded calls)."""
    return "steps" in trace and "admitted" in trace


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
