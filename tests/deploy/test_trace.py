"""The coordinator's optional trace: every shard call, its bytes and what it consumed, is
consistent with the render's own statistics (bench/network/netmodel.py replays it)."""

from __future__ import annotations

import pytest

from nprt.scene.demos import make_demo
from nprt.workers.render import render
from nprt.workers.runtime.coordinator import Coordinator
from nprt.workers.settings import RenderSettings

K = 3  # several targets per call, so the producer -> consumer matching is exercised


@pytest.fixture(scope="module")
def traced(ray_local):
    scene = make_demo("sculpture", "small")
    s = RenderSettings(width=48, height=32, spp=2, spp_per_pass=1, tile_size=32, bounces=3,
                       shards=K, seed=3)
    coord = Coordinator(scene, s, trace=True)
    try:
        result = render(scene, s, renderer=coord)
        return coord.trace.to_dict(), result.stats.to_dict(), coord
    finally:
        coord.close()


def test_every_consumed_output_comes_from_an_earlier_returned_call(traced):
    trace, _, _ = traced
    calls = trace["calls"]
    assert [c["call"] for c in calls] == list(range(len(calls)))
    consumed = 0
    for c in calls:
        assert c["return_s"] is not None and c["return_s"] >= c["dispatch_s"], c
        for producer, rays in c["inputs"]:
            p = calls[producer]
            assert producer < c["call"], (producer, c)
            assert p["return_s"] <= c["dispatch_s"], (p, c)  # routed after its manifest came
            assert rays > 0 and p["rays_out"][c["shard"]] > 0, (p, c)
            consumed += 1
    assert consumed > 0, "no call consumed a parcel: nothing crossed shards"


def test_every_output_is_consumed_exactly_once(traced):
    """Rays a call sent to shard t are the rays that later calls on t took from it."""
    calls = traced[0]["calls"]
    taken: dict[tuple[int, int], int] = {}
    for c in calls:
        for producer, rays in c["inputs"]:
            key = (producer, c["shard"])
            taken[key] = taken.get(key, 0) + rays
    sent = {(c["call"], t): r for c in calls for t, r in enumerate(c["rays_out"]) if r}
    assert taken == sent


def test_bytes_add_up_to_the_render_statistics(traced):
    trace, stats, coord = traced
    calls = trace["calls"]
    assert stats["total_bytes"] > 0
    assert sum(c["bytes_out"] for c in calls) == stats["total_bytes"]
    assert sum(c["bytes_in"] for c in calls) == stats["total_bytes"]
    for c in calls:
        assert sum(c["input_bytes"]) == c["bytes_in"], c
        assert len(c["input_bytes"]) == len(c["inputs"]), c
    # The same calls and busy time the coordinator counts per shard.
    for sid in range(K):
        mine = [c for c in calls if c["shard"] == sid]
        assert len(mine) == coord.calls[sid]
        assert sum(c["busy_s"] for c in mine) == pytest.approx(coord.busy_s[sid], rel=1e-9)

