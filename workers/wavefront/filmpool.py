"""The films of the passes live on a shard, in one array of slots.

A pass takes a slot on its first step here and keeps it until `collect`, so a step's splat
kernel adds every contribution to its pass's slot in one call over the batch, and no step
allocates or copies a film. (Giving each step a fresh (passes, pixels, 3, 2) array and
copying every pass's film in and out cost about 200 KB of zeroing and copying a pass a
step at 64-pixel tiles, which grows with passes x steps: many small steps over many passes
are what a shard on many cores runs.)

Threads: a step (the wavefront thread) takes slots and writes the slots of its passes;
`release` (a Ray thread running `collect`) reads and frees the slot of a finished pass,
which no step writes. Growing replaces the array, so take and release hold a lock. A
`clear` (a new run) frees every slot at once; a release of a slot taken before it is
refused, or a collect that raced the reset would free a slot a new pass holds.
"""

from __future__ import annotations

import threading

import numpy as np

from nprt.workers.filmsum import FilmSums
from nprt.workers.passes import Pass


class FilmPool:
    """words (slots, n, 3, 2) int64: film slot s of a pass with n_pixels <= n, in its tile's
    row-major pixel order; x0, y0, tile_w (slots,) int64: the tile of the pass in slot s."""

    def __init__(self, n: int):
        self.n = n
        self.words = np.zeros((0, n, 3, 2), np.int64)
        self.x0 = np.zeros(0, np.int64)
        self.y0 = np.zeros(0, np.int64)
        self.tile_w = np.zeros(0, np.int64)
        self._free: list[int] = []
        self._lock = threading.Lock()
        self.generation = 0  # clears so far: a slot is (index, generation)

    def take(self, p: Pass) -> tuple[int, int]:
        """A zeroed slot for pass p (its tile of at most n pixels): (index, generation)."""
        if p.n_pixels > self.n:
            raise ValueError(f"pass of {p.n_pixels} pixels in a pool of {self.n}-pixel slots")
        with self._lock:
            if not self._free:
                self._grow()
            s = self._free.pop()
            self.x0[s], self.y0[s], self.tile_w[s] = p.x0, p.y0, p.x1 - p.x0
            return s, self.generation

    def release(self, slot: tuple[int, int], n_pixels: int) -> FilmSums:
        """The film in `slot` (its first n_pixels), copied out; the slot is zeroed and free.
        A slot from before the last `clear` is refused (ValueError)."""
        s, generation = slot
        with self._lock:
            if generation != self.generation:
                raise ValueError(f"film slot {s} of clear {generation}, now {self.generation}")
            film = FilmSums(self.words[s, :n_pixels].copy())
            self.words[s] = 0
            self._free.append(s)
            return film

    def clear(self) -> None:
        """Every slot free and zeroed (a new job or a re-run: no pass state)."""
        with self._lock:
            self.words[...] = 0
            self._free = list(range(len(self.words)))[::-1]
            self.generation += 1

    def _grow(self) -> None:
        old = len(self.words)
        new = max(4, 2 * old)
        words = np.zeros((new, self.n, 3, 2), np.int64)
        words[:old] = self.words
        self.words = words
        self.x0, self.y0, self.tile_w = (np.concatenate([a, np.zeros(new - old, np.int64)])
                                         for a in (self.x0, self.y0, self.tile_w))
        self._free.extend(range(new - 1, old - 1, -1))
