"""Render statistics: rays, transfers and bytes by kind, hops, time per phase.

Every shard keeps one `RenderStats`; the coordinator merges them. Phase names are
the stage names of the wavefront loop. A phase records wall seconds (`phase_s`) and the
process's CPU seconds (`phase_cpu_s`, every thread of the process: onnxruntime's pool
included); phases nest (`proxy` runs inside `top_level`), and each records only its own
time, without its nested phases', so the phases of a shard add up to its busy time.
"""

from __future__ import annotations

import time
from collections import defaultdict

import numpy as np

from nprt.workers.runtime.protocol import KIND_NAMES

MAX_HOPS = 64


class _Phase:
    """`RenderStats.phase`: a plain context manager object (a generator-based one cost
    twice as much, and a step enters phases a few dozen times)."""

    __slots__ = ("stats", "name", "t0", "c0")

    def __init__(self, stats: RenderStats, name: str):
        self.stats, self.name = stats, name

    def __enter__(self) -> None:
        self.stats._open.append([0.0, 0.0])
        self.t0, self.c0 = time.perf_counter(), time.process_time()

    def __exit__(self, *exc) -> None:
        dt, dc = time.perf_counter() - self.t0, time.process_time() - self.c0
        st = self.stats
        inner = st._open.pop()
        st.phase_s[self.name] += dt - inner[0]
        st.phase_cpu_s[self.name] += dc - inner[1]
        if st._open:  # the enclosing phase does not count this one's time again
            st._open[-1][0] += dt
            st._open[-1][1] += dc


class RenderStats:
    def __init__(self):
        self.rays = defaultdict(int)  # kind name -> rays traced
        self.transfers = defaultdict(int)  # kind name -> rays sent shard to shard
        self.bytes = defaultdict(int)  # kind name -> bytes of those rays
        self.phase_s = defaultdict(float)  # stage name -> wall seconds, nested phases excluded
        self.phase_cpu_s = defaultdict(float)  # stage name -> process CPU seconds, the same way
        self.counters = defaultdict(int)  # anything else: mispredictions, fallbacks...
        self.hops = np.zeros(MAX_HOPS + 1, np.int64)  # rays finished after h transfers
        self._open: list[list[float]] = []  # running phases: [wall, cpu] of nested ones

    def phase(self, name: str) -> _Phase:
        """A context that adds its wall and CPU time to `name`, less its nested phases'."""
        return _Phase(self, name)

    def count_rays(self, kind: np.ndarray | int, n: int | None = None) -> None:
        """Count traced rays by kind: an array of kinds, or one kind and a count."""
        if isinstance(kind, np.ndarray):
            for k, c in enumerate(np.bincount(kind, minlength=3)[:3]):
                self.rays[KIND_NAMES[k]] += int(c)
        else:
            self.rays[KIND_NAMES[kind]] += int(n)

    def count_transfer(self, kind_name: str, n: int, nbytes: int) -> None:
        self.transfers[kind_name] += int(n)
        self.bytes[kind_name] += int(nbytes)

    def count_hops(self, hops: np.ndarray) -> None:
        self.hops += np.bincount(np.minimum(hops, MAX_HOPS), minlength=MAX_HOPS + 1)

    def merge(self, other: RenderStats) -> RenderStats:
        for mine, theirs in ((self.rays, other.rays), (self.transfers, other.transfers),
                             (self.bytes, other.bytes), (self.phase_s, other.phase_s),
                             (self.phase_cpu_s, other.phase_cpu_s),
                             (self.counters, other.counters)):
            for k, v in theirs.items():
                mine[k] += v
        self.hops += other.hops
        return self

    def to_dict(self) -> dict:
        last = int(np.flatnonzero(self.hops).max()) + 1 if self.hops.any() else 0
        return {
            "rays": {k: self.rays.get(k, 0) for k in KIND_NAMES},
            "transfers": {k: self.transfers.get(k, 0) for k in KIND_NAMES},
            "bytes": {k: self.bytes.get(k, 0) for k in KIND_NAMES},
            "total_transfers": int(sum(self.transfers.values())),
            "total_bytes": int(sum(self.bytes.values())),
            "hops_histogram": self.hops[:last].tolist(),
            "phase_s": {k: round(v, 6) for k, v in sorted(self.phase_s.items())},
            "phase_cpu_s": {k: round(v, 6) for k, v in sorted(self.phase_cpu_s.items())},
            "counters": dict(sorted(self.counters.items())),
        }

    @classmethod
    def from_dict(cls, d: dict) -> RenderStats:
        s = cls()
        for name in ("rays", "transfers", "bytes", "counters"):
            getattr(s, name).update(d.get(name, {}))
        s.phase_s.update(d.get("phase_s", {}))
        s.phase_cpu_s.update(d.get("phase_cpu_s", {}))
        h = d.get("hops_histogram", [])
        s.hops[:len(h)] = h
        return s


_EVERY = np.zeros(0, bool)  # add_pairs' mask for "every row"


def _add(out: np.ndarray, tok: np.ndarray, key, cap: int, mask=None) -> None:
    """out (t, w) int64 += 1 at [tok, min(key, cap)] of each row (where mask): key (n,) or
    one value for every row; tok (n,) int64."""
    # Imported here: the driver imports RenderStats from this module and must not import
    # numba (tests/test_driver_contract.py); only a shard's steps count with the kernels.
    from nprt.workers.kernels.counts import add_column, add_pairs

    tok = np.ascontiguousarray(tok, np.int64)
    for name, a in (("key", key), ("mask", mask)):
        if isinstance(a, np.ndarray) and a.shape != tok.shape:
            raise ValueError(f"{name}: expected shape {tok.shape} (the bound batch), "
                             f"got {a.shape}")
    if isinstance(key, np.ndarray):
        key = np.ascontiguousarray(key)
        if key.dtype != np.uint8:
            key = key.astype(np.int64)
        add_pairs(out, tok, key, cap, _EVERY if mask is None else np.ascontiguousarray(mask))
    elif mask is None:
        add_column(out, tok, min(int(key), cap))
    else:
        add_column(out, tok[mask], min(int(key), cap))


class SplitStats:
    """Statistics of one merged wavefront step over several passes. Counts go to the
    pass of each ray (a re-run pass drops exactly its own); stage times cannot be
    separated, so `finish` shares them out by rays traced.

    Counts are kept as (t, ...) arrays for the step and added to the passes' RenderStats
    once, in `finish`: a step calls the counters a dozen times, and a Python loop over
    the passes in each call made the step's cost grow with passes x calls (0.12 ms per
    pass per step, the largest part of a small step's glue on many cores).

    parts : (t,) RenderStats, one per pass; `bind(tok)` names the pass's index in parts
    (n,) int of every row of the batch that the next calls count (rows index it)."""

    def __init__(self, parts: list[RenderStats]):
        t = len(parts)
        self.parts = parts
        self.times = RenderStats()
        self.tok = np.zeros(0, np.int64)
        self._rays = np.zeros((t, 3), np.int64)  # per pass, per kind
        self._hops = np.zeros((t, MAX_HOPS + 1), np.int64)
        self._sent = np.zeros((t, 3), np.int64)  # transfers per pass, per kind
        self._sent_bytes = np.zeros((t, 3), np.int64)
        self._counters: dict[str, np.ndarray] = {}  # name -> (t,) int64

    def bind(self, tok: np.ndarray) -> SplitStats:
        self.tok = tok
        return self

    def phase(self, name: str):
        return self.times.phase(name)

    def _per_part(self, rows) -> np.ndarray:
        """(t,) int64 rows of the bound batch per attempt (rows: mask, indices or all)."""
        tok = self.tok if rows is None else self.tok[rows]
        return np.bincount(tok, minlength=len(self.parts))

    def count(self, name: str, rows=None) -> None:
        per = self._per_part(rows)
        have = self._counters.get(name)
        self._counters[name] = per if have is None else have + per

    def count_rays(self, kind: np.ndarray | int) -> None:
        """kind : (n,) uint8 of the bound batch's rows, or one kind for them all. One pass
        over the rows (`add_pairs`): O(n) for any number of passes in the step."""
        _add(self._rays, self.tok, kind, 2)

    def count_hops(self, hops: np.ndarray, rows=None) -> None:
        """hops : (n,) of the bound batch; rows: which of them finished (mask or indices)."""
        tok = self.tok
        if rows is not None:
            rows = np.asarray(rows)
            if rows.dtype != bool:
                tok, hops, rows = np.take(tok, rows), np.take(hops, rows), None
        _add(self._hops, tok, hops, MAX_HOPS, rows)

    def count_transfers(self, kind: np.ndarray | int, per_row: int) -> None:
        """Rays of the bound batch sent to another shard: kind (n,) int of each row (or one
        for them all), per_row bytes each."""
        per = np.zeros_like(self._sent)
        _add(per, self.tok, kind, 2)
        self._sent += per
        self._sent_bytes += per * per_row

    def finish(self) -> None:
        """Add the step's counts to each pass's RenderStats, and its phase times shared
        out by rays traced. Plain Python numbers throughout (`tolist`): a step holds
        dozens of passes, and numpy scalars and a nonzero scan per pass and kind cost more
        than the counting itself."""
        traced = self._rays.sum(axis=1)
        share = (traced / traced.sum() if traced.sum() else
                 np.full(len(self.parts), 1.0 / max(len(self.parts), 1))).tolist()
        rays, sent, sent_bytes = (a.tolist() for a in (self._rays, self._sent,
                                                        self._sent_bytes))
        hopped = self._hops.any(axis=1).tolist()
        counters = [(name, per.tolist()) for name, per in self._counters.items()]
        phases = list(self.times.phase_s.items())
        cpu = list(self.times.phase_cpu_s.items())
        for j, (part, w) in enumerate(zip(self.parts, share, strict=True)):
            for k, name in enumerate(KIND_NAMES):
                if rays[j][k]:
                    part.rays[name] += rays[j][k]
                if sent[j][k]:
                    part.count_transfer(name, sent[j][k], sent_bytes[j][k])
            if hopped[j]:
                part.hops += self._hops[j]
            for name, per in counters:
                if per[j]:
                    part.counters[name] += per[j]
            for name, s in phases:
                part.phase_s[name] += s * w
            for name, s in cpu:
                part.phase_cpu_s[name] += s * w
