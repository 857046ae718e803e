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


def _run(scene, k: int, emit: int, hold=(0, 0.0), send=(0, 0.0)) -> dict:
    s = RenderSettings(width=32, height=24, spp=2, spp_per_pass=1, tile_size=16, seed=1,
                       shards=k)
    return simulate(shards_in_process(scene, s, warm=False), s, COST, 0.005, 25e9, emit,
                    hold, send)


def test_every_k_and_emit_gives_the_one_shard_film(scene):
    one = _run(scene, 1, 0)
    assert one["parcels"] == 0 and np.abs(one["film"]).sum() > 0
    # (1 << 30) rays never come: every step with rays but no orders holds all 20 ms
    for k, emit, hold in ((2, 0, (0, 0.0)), (2, 1, (0, 0.0)), (3, 1, (1 << 30, 0.02))):
        r = _run(scene, k, emit, hold)
        assert np.array_equal(r["film"], one["film"]), (k, emit, hold)
        assert r["parcels"] > 0
        assert (r["early_parcels"] > 0) == (emit > 0)


def test_the_wall_lies_between_the_busiest_shard_and_all_of_them(scene):
    r = _run(scene, 3, 1)
    assert r["busy_s"].max() <= r["wall_s"] <= r["busy_s"].sum() + 1.0  # latency: < 1 s here


def test_a_hold_that_never_fills_delays_each_step_by_its_length(scene):
    """Every step with parcels and no orders waits the whole hold: the wall grows by at
    least one hold a hop on the longest chain, and no more than one a step."""
    free, held = _run(scene, 2, 0), _run(scene, 2, 0, (1 << 30, 0.05))
    assert np.array_equal(free["film"], held["film"])
    assert free["wall_s"] + 0.05 <= held["wall_s"] <= free["wall_s"] + 0.05 * held["steps"]


def test_the_outbox_holds_small_parcels_and_the_film_stays_the_same(scene):
    """With the runtime's Outbox on the virtual clock: parcels that never fill and never
    age out leave only when nothing has reached their shard by a step's end (the flush),
    so fewer of them leave, nothing stalls, and the film is the one-shard film."""
    one, free = _run(scene, 1, 0), _run(scene, 3, 1)
    for send in ((1 << 30, 100.0), (64, 0.01)):
        r = _run(scene, 3, 1, send=send)
        assert np.array_equal(r["film"], one["film"]), send
        assert 0 < r["parcels"] < free["parcels"], send
