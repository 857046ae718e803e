"""A render is a sequence of passes, one per tile and sample chunk; a pass is the unit of
progress, of resumption after a restart, and of retry after a shard dies.

Passes are computed from their index, never listed: a job of 1e9 passes costs nothing to
accept, and a render walks its passes lazily."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from nprt.workers.settings import RenderSettings


@dataclass(frozen=True)
class Pass:
    index: int
    x0: int
    y0: int
    x1: int
    y1: int
    sample0: int
    sample1: int

    def pixels(self, width: int) -> np.ndarray:
        """(p,) uint32 linear pixel indices y * width + x of this tile, row-major."""
        ys, xs = np.mgrid[self.y0:self.y1, self.x0:self.x1]
        return (ys.ravel() * width + xs.ravel()).astype(np.uint32)

    def local_index(self, pixel: np.ndarray, width: int) -> np.ndarray:
        """(n,) uint32 image pixel indices -> (n,) int64 row-major indices within the tile."""
        x = pixel.astype(np.int64) % width - self.x0
        y = pixel.astype(np.int64) // width - self.y0
        return y * (self.x1 - self.x0) + x

    @property
    def n_pixels(self) -> int:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    @property
    def n_paths(self) -> int:
        return (self.x1 - self.x0) * (self.y1 - self.y0) * (self.sample1 - self.sample0)


def _grid(s: RenderSettings) -> tuple[int, int, int]:
    """(tiles across, tiles down, sample chunks)."""
    return (-(-s.width // s.tile_size), -(-s.height // s.tile_size),
            -(-s.spp // s.spp_per_pass))


def count_tiles(s: RenderSettings) -> int:
    tx, ty, _ = _grid(s)
    return tx * ty


def tile_of(s: RenderSettings, pixel: np.ndarray) -> np.ndarray:
    """(n,) uint32 linear pixel indices -> (n,) int64 tile index (row-major tile grid).
    Pass `index` covers tile `index % count_tiles(s)`."""
    pixel = np.asarray(pixel, np.int64)
    ts, tx = s.tile_size, -(-s.width // s.tile_size)
    return (pixel // s.width // ts) * tx + (pixel % s.width) // ts


def count_passes(s: RenderSettings) -> int:
    tx, ty, chunks = _grid(s)
    return tx * ty * chunks


def pass_at(s: RenderSettings, index: int) -> Pass:
    """Pass `index` in render order: sample chunks outermost, so a partial image covers the
    whole frame early; tiles row-major within a chunk."""
    tx, ty, chunks = _grid(s)
    if not 0 <= index < tx * ty * chunks:
        raise IndexError(f"pass {index} out of range 0..{tx * ty * chunks - 1}")
    chunk, tile = divmod(index, tx * ty)
    y, x = divmod(tile, tx)
    x0, y0, s0 = x * s.tile_size, y * s.tile_size, chunk * s.spp_per_pass
    return Pass(index, x0, y0, min(s.width, x0 + s.tile_size), min(s.height, y0 + s.tile_size),
                s0, min(s.spp, s0 + s.spp_per_pass))


def iter_passes(s: RenderSettings, start: int = 0, skip: Iterable[int] = ()) -> Iterator[Pass]:
    """Passes from `start` on, in order, leaving out the indices in `skip`."""
    skip = set(skip)
    for i in range(start, count_passes(s)):
        if i not in skip:
            yield pass_at(s, i)
