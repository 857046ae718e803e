"""bench/render/vtime.py: K in-process shards in virtual time render the one-shard film bit
for bit (exact mode), with or without sends during a step, and its wall is bounded by the
shards' busy time as a schedule on K cores must be."""

from __future__ import annotations

import numpy as np
import pytest

from bench.render.vtime import simulate
from nprt.scene.store import open_scene
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process

COST = {"send_s": 4e-4, "send_s_per_byte": 1e-9, "receive_s": 4e-4, "receive_s_per_byte": 1e-9}


@pytest.fixture(scope="module")
def scene():
    return open_scene("forest:tiny").load()


def _run(scene, k: int, emit: int) -> dict:
    s = RenderSettings(width=32, height=24, spp=2, spp_per_pass=1, tile_size=16, seed=1,
                       shards=k)
    return simulate(shards_in_process(scene, s, warm=False), s, COST, 0.005, 25e9, emit)


def test_every_k_and_emit_gives_the_one_shard_film(scene):
    one = _run(scene, 1, 0)
    assert one["parcels"] == 0 and np.abs(one["film"]).sum() > 0
    for k, emit in ((2, 0), (2, 1), (3, 1)):
        r = _run(scene, k, emit)
        assert np.array_equal(r["film"], one["film"]), (k, emit)
        assert r["parcels"] > 0
        assert (r["early_parcels"] > 0) == (emit > 0)


def test_the_wall_lies_between_the_busiest_shard_and_all_of_them(scene):
    r = _run(scene, 3, 1)
    assert r["busy_s"].max() <= r["wall_s"] <= r["busy_s"].sum() + 1.0  # latency: < 1 s here
