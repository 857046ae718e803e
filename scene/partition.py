"""Partitioning objects (a base mesh with its instances) across K shards so that every shard
has about the same ray work (nprt.scene.workload's estimate), each shard's bytes capped near
what a bytes-only partition would give; objects are split into spatially coherent pieces
where one is too much work for one shard, or there are more shards than meshes.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from nprt.scene.errors import SceneError
from nprt.scene.model import Scene, instance_world_bounds
from nprt.scene.workload import instance_work

SHARD_DTYPE = np.int32
# The default cap on a shard's bytes, in units of the bytes-only rule's largest shard
# (`RenderSettings.byte_slack` sets it per job): wider lets placement balance ray work where
# meshes are few and alike in size (city at K = 8), at the cost of memory.
BYTE_SLACK = 1.25
BALANCED = 0.02  # the busiest shard's work within this of the fair share ends the search
MAX_PIECES_PER_SHARD = 4  # pieces in all, per shard: each is another box boundary to cross
IMPROVE_STEPS = 8  # local-search moves per shard at most
TIGHTER = 4  # packings tried, the cap tightened in steps down to the bytes-only maximum


@dataclass(frozen=True, eq=False)
class Partition:
    """Which shard owns each instance, and which base meshes each shard holds.

    instance_shard : (n_instances,) int32, owning shard of each instance
    shard_meshes   : per shard, the sorted mesh indices it holds
    shard_bytes    : (k,) int64, geometry bytes per shard (each held mesh counted once)
    shard_work     : (k,) float64, estimated ray work per shard (replicated meshes left out)
    byte_cap       : the bytes of its own pieces a shard may hold (byte_slack x the
                     bytes-only rule's largest shard, at least the largest mesh); no shard
                     holds more, the replicated meshes coming on top
    bytes_only_max : the largest shard's bytes under the bytes-only rule, for comparison
    bytes_only_work : (k,) float64, estimated work per shard under that rule
    """

    k: int
    instance_shard: np.ndarray
    shard_meshes: tuple[tuple[int, ...], ...]
    shard_bytes: np.ndarray
    shard_work: np.ndarray
    byte_cap: int
    bytes_only_max: int
    bytes_only_work: np.ndarray

    @property
    def max_shard_bytes(self) -> int:
        """The most geometry memory any one shard holds (the paper's "most memory among nodes")."""
        return int(self.shard_bytes.max())

    def shard_instances(self, shard: int) -> np.ndarray:
        """(m,) int64 indices of the instances owned by `shard`, ascending."""
        return np.flatnonzero(self.instance_shard == shard)

    def mesh_shards(self, mesh: int) -> tuple[int, ...]:
        """The shards holding base mesh `mesh` (several when its instances were split)."""
        return tuple(s for s, held in enumerate(self.shard_meshes) if mesh in held)

    def summary(self) -> dict:
        mean = float(self.shard_bytes.mean())
        held = [m for ms in self.shard_meshes for m in ms]
        return {
            "k": self.k,
            "shard_bytes": self.shard_bytes.tolist(),
            "max_shard_bytes": self.max_shard_bytes,
            "bytes_only_max_shard_bytes": self.bytes_only_max,
            "byte_cap": self.byte_cap,
            "total_shard_bytes": int(self.shard_bytes.sum()),
            "imbalance": round(self.max_shard_bytes / mean, 4) if mean > 0 else 1.0,
            "shard_work": np.round(self.shard_work, 4).tolist(),
            "work_imbalance": _ratio(self.shard_work),
            "bytes_only_work_imbalance": _ratio(self.bytes_only_work),
            "instances_per_shard": np.bincount(self.instance_shard, minlength=self.k).tolist(),
            "meshes_per_shard": [len(ms) for ms in self.shard_meshes],
            "split_meshes": sorted({m for m in held if held.count(m) > 1}),
        }


def partition(scene: Scene, k: int, replicated=(), work=None,
              byte_slack: float = BYTE_SLACK) -> Partition:
    """Assign every instance to one of k shards, balancing estimated ray work under a cap
    on each shard's bytes.

    The rule:
    1. Pieces. Every instanced mesh is one piece, and while there are fewer pieces than
       shards the mesh with the most work per piece is cut into one more. A mesh's pieces
       are spatially coherent groups of near-equal work, from recursive weighted-median
       bisection of the instance centres along the longest axis.
    2. Cap. byte_cap = byte_slack x the largest shard of the bytes-only rule (the same
       pieces, largest mesh first to the shard with the fewest bytes), and at least the
       largest mesh. That packing is the fallback: it always fits.
    3. Pack by work, largest piece first, each to the least-loaded shard it fits in under
       the cap (a mesh already held costs no bytes); where a piece would overflow, a
       tighter cap is tried. Then a local search moves a piece off the busiest shard, or
       swaps it for a lighter one, while that lowers the larger of the two shards' work.
    4. Cut the mesh of the busiest shard's heaviest piece once more and pack again, until
       the busiest shard is within BALANCED of the fair share (total work / k), no piece
       there can be cut (one instance each), or there are MAX_PIECES_PER_SHARD x k pieces.
       The packing with the least work on its busiest shard (under the cap) is kept.
    Every shard gets at least one piece.

    work: (n_instances,) float64 per-instance ray work; None: nprt.scene.workload's
    `instance_work` (metadata only). replicated: mesh indices every shard will hold
    (placement's choice for meshes too light to be worth forwarding rays to): they take no
    piece, every shard holds them, and their instances are recorded on shard 0 (the
    placement owns them everywhere). Ignored where the other meshes have fewer than k
    instances. byte_slack: the cap of step 2, >= 1 (1: no shard above the bytes-only rule's
    largest).
    """
    n = len(scene.instances)
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise SceneError(f"partition: shard count must be an integer >= 1, got {k!r}")
    if k > n:
        raise SceneError(
            f"partition: cannot give {k} shards at least one instance each; "
            f"scene {scene.name!r} has only {n} instances (use k <= {n})"
        )
    if not np.isfinite(byte_slack) or byte_slack < 1.0:
        raise SceneError(f"partition: byte_slack must be a finite number >= 1, got "
                         f"{byte_slack!r}")
    k = int(k)
    inst_mesh = np.asarray(scene.instance_mesh, dtype=np.int64)
    counts = np.bincount(inst_mesh, minlength=len(scene.meshes))
    nbytes = np.array([m.nbytes for m in scene.meshes], dtype=np.int64)
    work = instance_work(scene) if work is None else np.asarray(work, np.float64)
    if work.shape != (n,) or not np.isfinite(work).all() or (work < 0).any():
        raise SceneError(f"partition: work must be ({n},) finite and >= 0, got shape "
                         f"{work.shape}")
    everywhere = np.isin(np.arange(len(scene.meshes)), np.asarray(replicated, np.int64))
    if counts[~everywhere].sum() < k:
        everywhere[:] = False
    used = np.flatnonzero(counts * ~everywhere)
    mesh_work = np.bincount(inst_mesh, weights=work, minlength=len(scene.meshes))
    pieces = _piece_counts(used, counts, nbytes, mesh_work, k)
    centres = instance_world_bounds(scene).mean(axis=1)  # (n, 3) float64
    # Instances grouped by mesh, ascending within a mesh: one sort, not a scan per mesh.
    by_mesh = np.argsort(inst_mesh, kind="stable")
    ends = np.cumsum(counts)
    cut: dict = {}  # (mesh, pieces) -> its groups

    def items_of(pieces: dict) -> list:
        """(mesh, piece, instance indices, work) of every piece."""
        out = []
        for m in used:
            key = (int(m), pieces[m])
            if key not in cut:
                idx = by_mesh[ends[m] - counts[m]:ends[m]]
                cut[key] = _bisect(centres, work, idx, pieces[m])
            out += [(int(m), p, g, float(work[g].sum())) for p, g in enumerate(cut[key])]
        return out

    # The bytes-only rule (largest mesh first to the shard with the fewest bytes) sets the
    # cap, and is the fallback: it always fits.
    items = sorted(items_of(pieces), key=lambda it: (-nbytes[it[0]], it[0], it[1]))
    shard_of, load, shard_work = _assign(items, nbytes, k, None)
    bytes_only, bytes_only_work = int(load.max()), shard_work
    cap = int(max(byte_slack * bytes_only, nbytes[used].max()))
    fair = max(float(work[np.isin(inst_mesh, used)].sum()) / k, 1e-300)

    def score(load, shard_work):
        return (max(int(load.max()) - cap, 0), round(float(shard_work.max()) / fair, 3),
                int(load.max()))

    best = (score(load, shard_work), items, shard_of, load, shard_work)
    while True:
        items = sorted(items, key=lambda it: (-it[3], it[0], it[1]))
        # A piece that fits nowhere overflows the cap; packing to a tighter cap keeps room.
        for tight in np.linspace(cap, bytes_only, TIGHTER + 1):
            shard_of, load, shard_work = _assign(items, nbytes, k, int(tight))
            if load.max() <= cap:
                break
        else:  # start from the bytes-only packing of these pieces, which fits
            by_bytes = sorted(range(len(items)), key=lambda i: (-nbytes[items[i][0]], i))
            got = _assign([items[i] for i in by_bytes], nbytes, k, None)[0]
            shard_of = [0] * len(items)
            for i, sh in zip(by_bytes, got, strict=True):
                shard_of[i] = sh
        shard_of, load, shard_work = _improve(items, shard_of, nbytes, k, cap)
        if score(load, shard_work) < best[0]:
            best = (score(load, shard_work), items, shard_of, load, shard_work)
        # Cut the mesh of the busiest shard's heaviest piece that can still be cut.
        busiest = int(np.argmax(shard_work))
        can = [it for it, s in zip(items, shard_of, strict=True)
               if s == busiest and pieces[it[0]] < counts[it[0]]]
        if (not can or len(items) >= MAX_PIECES_PER_SHARD * k
                or shard_work.max() <= (1 + BALANCED) * fair):
            break
        pieces[can[0][0]] += 1
        items = items_of(pieces)
    _, items, shard_of, load, shard_work = best

    instance_shard = np.empty(n, dtype=SHARD_DTYPE)
    held: list[set[int]] = [set() for _ in range(k)]
    for (m, _, group, _), s in zip(items, shard_of, strict=True):
        instance_shard[group] = s
        held[s].add(m)
    load = load.copy()
    for m in np.flatnonzero(everywhere & (counts > 0)):
        instance_shard[inst_mesh == m] = 0
        for h in held:
            h.add(int(m))
        load += nbytes[m]
    for a in (instance_shard, load, shard_work, bytes_only_work):
        a.setflags(write=False)
    return Partition(k, instance_shard, tuple(tuple(sorted(h)) for h in held), load,
                     shard_work, cap, bytes_only, bytes_only_work)


def _ratio(work: np.ndarray) -> float:
    """The busiest shard's work over the mean."""
    mean = float(work.mean())
    return round(float(work.max()) / mean, 4) if mean > 0 else 1.0


def _assign(items: list, nbytes: np.ndarray, k: int, cap):
    """Greedy assignment of pieces (mesh, piece, instances, work), in the order given, to
    k shards. cap None: the bytes-only rule, each piece to the shard with the fewest bytes.
    Else each piece goes to the shard with the least work that it fits in under `cap` (a
    mesh already held costs no bytes), or, fitting nowhere, where bytes grow least; the
    last pieces fill the shards still empty.
    returns shard of each piece (list), bytes (k,) int64 and work (k,) float64 per shard
    """
    held: list[set[int]] = [set() for _ in range(k)]
    load = np.zeros(k, dtype=np.int64)
    done = np.zeros(k)
    out = []
    for i, (m, _, _, w) in enumerate(items):
        grow = np.array([0 if m in h else nbytes[m] for h in held], dtype=np.int64)
        empty = np.array([not h for h in held])
        fits = load + grow <= (np.inf if cap is None else cap)
        if empty.sum() >= len(items) - i:  # as many pieces left as empty shards
            s = int(np.flatnonzero(empty)[0])
        elif cap is None:
            s = int(np.argmin(load))
        elif fits.any():
            s = int(np.flatnonzero(fits)[np.argmin(done[fits])])
        else:
            s = int(np.argmin(load + grow))
        out.append(s)
        held[s].add(m)
        load[s] += grow[s]
        done[s] += w
    return out, load, done


def _improve(items: list, shard_of: list, nbytes: np.ndarray, k: int, cap: int):
    """Local search on an assignment: move one piece off the busiest shard, or swap it for a
    lighter one, where that lowers the larger of the two shards' work and keeps both within
    `cap` (or no worse than they were); until no move helps.
    returns shard of each piece (list), bytes (k,) int64 and work (k,) float64 per shard
    """
    shard_of = list(shard_of)
    w = np.array([it[3] for it in items])
    mesh = [it[0] for it in items]
    n_held = [dict() for _ in range(k)]  # shard -> mesh -> pieces held
    for i, s in enumerate(shard_of):
        n_held[s][mesh[i]] = n_held[s].get(mesh[i], 0) + 1
    load = np.array([sum(int(nbytes[m]) for m in h) for h in n_held], dtype=np.int64)
    done = np.bincount(shard_of, weights=w, minlength=k)

    def bytes_after(s, out, into):
        """Shard s's bytes after pieces `out` leave it and `into` arrive."""
        held = dict(n_held[s])
        for i in out:
            held[mesh[i]] -= 1
        for i in into:
            held[mesh[i]] = held.get(mesh[i], 0) + 1
        return sum(int(nbytes[m]) for m, c in held.items() if c > 0)

    for _ in range(IMPROVE_STEPS * k):
        s = int(np.argmax(done))
        on = [[] for _ in range(k)]  # pieces per shard, lightest first
        for i in sorted(range(len(items)), key=lambda i: (w[i], i)):
            on[shard_of[i]].append(i)
        best = (done[s], None)
        for i in (on[s] if len(on[s]) > 1 else ()):  # a shard keeps at least one piece
            for t in range(k):
                if t == s:
                    continue
                # The swap partner that evens s and t best weighs w_i - (done_s - done_t) / 2:
                # try the move and the pieces of t either side of that weight.
                ws = [w[j] for j in on[t]]
                at = int(np.searchsorted(ws, w[i] - (done[s] - done[t]) / 2))
                for j in [None] + on[t][max(at - 1, 0):at + 1]:
                    dw = w[i] - (0.0 if j is None else w[j])
                    peak = max(done[s] - dw, done[t] + dw)
                    if peak >= best[0] - 1e-12:
                        continue
                    back = () if j is None else (j,)
                    bs, bt = bytes_after(s, (i,), back), bytes_after(t, back, (i,))
                    if bs <= max(cap, load[s]) and bt <= max(cap, load[t]):
                        best = (peak, (i, j, t, bs, bt))
        if best[1] is None:
            break
        i, j, t, bs, bt = best[1]
        moves = [(i, s, t)] + ([] if j is None else [(j, t, s)])
        for p, a, b in moves:
            shard_of[p] = b
            n_held[a][mesh[p]] -= 1
            if not n_held[a][mesh[p]]:
                del n_held[a][mesh[p]]
            n_held[b][mesh[p]] = n_held[b].get(mesh[p], 0) + 1
            done[a] -= w[p]
            done[b] += w[p]
        load[s], load[t] = bs, bt
    return shard_of, load, done


def _piece_counts(used: np.ndarray, counts: np.ndarray, nbytes: np.ndarray,
                  work: np.ndarray, k: int) -> dict:
    """Pieces per instanced mesh summing to max(k, len(used)): extra pieces go, one at a time,
    to the mesh with the most work per piece (work: (meshes,) float64; ties: more instances
    per piece, more bytes, then lower index). A mesh is cut into at most one piece per
    instance."""
    pieces = {int(m): 1 for m in used}
    heap = [(-float(work[m]), -float(counts[m]), -int(nbytes[m]), int(m))
            for m in used if counts[m] > 1]
    heapq.heapify(heap)
    for _ in range(k - len(used)):
        _, _, neg_bytes, m = heapq.heappop(heap)  # never empty: k <= number of instances
        pieces[m] += 1
        if pieces[m] < counts[m]:
            heapq.heappush(heap, (-work[m] / pieces[m], -counts[m] / pieces[m], neg_bytes, m))
    return pieces


def _bisect(centres: np.ndarray, work: np.ndarray, idx: np.ndarray,
            parts: int) -> list[np.ndarray]:
    """Split instance indices into `parts` spatially coherent groups of near-equal work.

    centres : (n, 3) float64 world centres of all instances; work : (n,) float64 per
    instance; idx : (m,) int64, m >= parts. Groups come in spatial order along each cut.
    """
    if parts == 1:
        return [idx]
    c = centres[idx]
    axis = int(np.argmax(np.ptp(c, axis=0)))
    order = idx[np.argsort(c[:, axis], kind="stable")]
    left = parts // 2
    acc = np.cumsum(work[order])  # (m,) work up to and including each instance
    total = acc[-1]
    # The cut with the left part's share of the work; with no work, of the instances.
    want = total * left / parts if total > 0 else None
    cut = (int(np.searchsorted(acc, want)) + 1 if want is not None
           else round(len(idx) * left / parts))
    cut = int(np.clip(cut, left, len(idx) - (parts - left)))
    return (_bisect(centres, work, order[:cut], left)
            + _bisect(centres, work, order[cut:], parts - left))
