"""Film sums that do not depend on how a pass's contributions were split: across steps
(timing) or across shards (K). Exact mode then equals the single-process reference bit for
bit at any K, and a faulted run gives the same bytes as an unfaulted one.

Every contribution is rounded once to an integer multiple of a fixed quantum, 2^LSB_EXP,
and the integers are added exactly (integer addition is associative). A shard returns its
pass's integer sums; the coordinator adds the shards' integers and converts to float64 once.
The quantum must not depend on the values (a per-shard scale would round differently at
each K), so the integers are wide: two int64 words of WORD_BITS bits per pixel and channel,
for |value| below 2^MAX_EXP (about 1.1e12). A contribution beyond that, or not finite, is
added in float64 to `rest` in a canonical order within a shard (those pixels match across K
only to float rounding; a radiance above 1e12 is not a path tracer's usual day).

This module is numpy only (the driver adds and converts); the shard's accumulation is the
numba kernel nprt.workers.kernels.filmsum.accumulate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LSB_EXP = -70  # the quantum: 2^-70 ~ 8.5e-22 absolute, far below float32 pixels' precision
WORD_BITS = 60  # [hi, lo]: value = (hi * 2^60 + lo) * 2^LSB_EXP, 0 <= lo < 2^60
# |value| < 2^40: hi < 2^50 per value, so a pixel's hi cannot overflow before 2^13 such.
MAX_EXP = LSB_EXP + 2 * WORD_BITS - 10
_LO_MASK = (1 << WORD_BITS) - 1


@dataclass(eq=False)
class FilmSums:
    """One pass's film (or one shard's share of it) as exact integers.

    words : (n, 3, 2) int64, [hi, lo] per pixel and channel, lo normalised to [0, 2^60);
    rest  : (n, 3) float64 sums of the contributions the words cannot hold, or None."""

    words: np.ndarray
    rest: np.ndarray | None = None

    @classmethod
    def zeros(cls, n: int) -> FilmSums:
        return cls(np.zeros((n, 3, 2), np.int64))

    def __iadd__(self, other: FilmSums) -> FilmSums:
        """Add another share of the same pixels; the same integers in any order."""
        w = self.words
        w += other.words
        w[..., 0] += w[..., 1] >> WORD_BITS  # carry (arithmetic shift: lo stays >= 0)
        w[..., 1] &= _LO_MASK
        if other.rest is not None:
            self.rest = other.rest.copy() if self.rest is None else self.rest + other.rest
        return self

    def to_float(self) -> np.ndarray:
        """(n, 3) float64: hi and lo scaled (exact powers of two) and added once."""
        out = np.ldexp(self.words[..., 0].astype(np.float64), LSB_EXP + WORD_BITS)
        out += np.ldexp(self.words[..., 1].astype(np.float64), LSB_EXP)
        if self.rest is not None:
            out += self.rest
        return out

    @property
    def nbytes(self) -> int:
        return self.words.nbytes + (0 if self.rest is None else self.rest.nbytes)
