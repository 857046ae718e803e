"""The step's pixel-to-pass kernels (nprt.workers.kernels.tiles) against the pass grid's
own definitions (`tile_of`, `Pass.local_index`), including narrow edge tiles."""

from __future__ import annotations

import numpy as np

from nprt.workers.kernels import tiles
from nprt.workers.passes import count_tiles, pass_at, tile_of
from nprt.workers.settings import RenderSettings


def test_pass_slots_and_tile_index_match_the_pass_grid_on_edge_tiles():
    s = RenderSettings(width=203, height=77, spp=4, tile_size=32)  # right and bottom tiles cut
    pixel = np.arange(s.width * s.height, dtype=np.uint32)
    slot_of_tile = np.random.default_rng(0).permutation(count_tiles(s)).astype(np.int64)
    assert np.array_equal(tiles.pass_slots(pixel, s.width, s.tile_size, slot_of_tile),
                          slot_of_tile[tile_of(s, pixel)])
    local = tiles.tile_index(pixel, s.width, s.tile_size)
    tile = tile_of(s, pixel)
    for k in range(count_tiles(s)):
        p, rows = pass_at(s, k), tile == k
        assert np.array_equal(local[rows], p.local_index(pixel[rows], s.width))
        assert np.array_equal(np.sort(local[rows]), np.arange(p.n_pixels))
