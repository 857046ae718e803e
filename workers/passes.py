"""A render is a list of passes, one per tile and sample chunk; a pass is the unit of
progress, of resumption after a restart, and of retry after a shard dies."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.settings import RenderSettings


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


def plan_passes(s: RenderSettings) -> list[Pass]:
    """Sample chunks outermost, so a partial image covers the whole frame early."""
    out = []
    for s0 in range(0, s.spp, s.spp_per_pass):
        s1 = min(s.spp, s0 + s.spp_per_pass)
        for y0 in range(0, s.height, s.tile_size):
            for x0 in range(0, s.width, s.tile_size):
                out.append(Pass(len(out), x0, y0, min(s.width, x0 + s.tile_size),
                                min(s.height, y0 + s.tile_size), s0, s1))
    return out


def count_passes(s: RenderSettings) -> int:
    """len(plan_passes(s)) in O(1): sample chunks times tiles."""
    def ceil_div(a: int, b: int) -> int:
        return -(-a // b)

    return (ceil_div(s.spp, s.spp_per_pass) * ceil_div(s.height, s.tile_size)
            * ceil_div(s.width, s.tile_size))
